"""The learned correction as a GTSAM factor you can drop into your own graph.

Example (any graph whose variable at ``key`` is an ECEF ``Point3``)::

    from learned.infer import Corrector
    from learned.factor import learned_prior_factor

    corrector = Corrector.load()                      # shipped weights, or Corrector.load("my.pt")
    factor, mean, cov = learned_prior_factor(corrector, sat_pos, pr, mask, init_pos, gtsam.symbol("x", k),
                                             pr_sigma=pr_sigma)
    graph.add(factor)

For a ``Pose3`` variable use :func:`learned_pose_translation_factor` (a ``PoseTranslationPrior3D``
on the pose's translation, i.e. the pose frame is ECEF). :func:`learned_prior_factors` does a whole
trace in one network pass (much faster than one call per epoch).
``examples/04_learned_factor_in_your_graph.py`` composes it with an odometry chain.

The per-satellite head as factors: :func:`learned_pseudorange_factors` gives GTSAM ``PseudorangeFactor``s
whose noise (and bias) the network predicts for each measurement (``examples/05_learned_pseudorange_factors.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.factors import prior_noise_model, robust_model
from fusion.estimate.graph.priors import PRIOR_MIN_EIG, PriorProvider, Priors, ask_provider, clean_priors
from fusion.trace import SIGNALS, Trace, empty_trace


def one_epoch_trace(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray, pr_sigma: np.ndarray | None = None,
                    signal: np.ndarray | None = None, t_ms: int = 0, name: str = "epoch",
                    cn0: np.ndarray | None = None) -> Trace:
    """Wrap one epoch's measurements (S satellites) as a 1-epoch :class:`Trace`.

    sat_pos (S,3) transmit-time ECEF [m]; pr (S,) corrected pseudoranges [m]; mask (S,) bool;
    pr_sigma (S,) the receiver's reported pseudorange sigma [m] (default 1); signal (S,) names from
    :data:`fusion.trace.SIGNALS` or their indices (default GPS_L1); cn0 (S,) [dB-Hz], 0 = unknown (default).
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
    for label, extra in (("pr_sigma", pr_sigma), ("signal", signal), ("cn0", cn0)):
        if extra is not None and np.shape(extra) != (S,):
            raise GeometryError(f"{name}: {label} must have shape ({S},) like pr, got {np.shape(extra)}")
    if pr_sigma is not None:
        kw["pr_sigma"] = _finite_on(mask, pr_sigma, "pr_sigma", name, filler=1.0, positive=True)[None]
    if cn0 is not None:
        kw["cn0"] = _finite_on(mask, cn0, "cn0", name, filler=0.0, positive=False)[None]
    if signal is not None:
        kw["signal"] = _signal_indices(signal, name)[None]
    return Trace(**kw)


def _finite_on(mask: np.ndarray, values, label: str, name: str, filler: float, positive: bool) -> np.ndarray:
    """(S,) float ``values`` on real slots ``mask`` (S,), ``filler`` on padding; GeometryError where a real
    slot's value is not finite (or not > 0 when ``positive``)."""
    v = np.asarray(values, float)
    bad = mask & ~(np.isfinite(v) & ((v > 0) if positive else True))
    if bad.any():
        raise GeometryError(f"{name}: {label} must be finite{' and > 0' if positive else ''} on real slots; "
                            f"slot {int(np.flatnonzero(bad)[0])} is {v[bad][0]}")
    return np.where(mask, v, filler)


def _signal_indices(signal, name: str) -> np.ndarray:
    """(S,) int8 indices into :data:`fusion.trace.SIGNALS` from names or indices (S,)."""
    sig = np.asarray(signal)
    if sig.dtype.kind in "UO":
        unknown = sorted({str(s) for s in sig} - set(SIGNALS))
        if unknown:
            raise GeometryError(f"{name}: unknown signal(s) {unknown} (known: {', '.join(SIGNALS)})")
        return np.array([SIGNALS.index(str(s)) for s in sig], np.int8)
    if sig.dtype.kind not in "iu" or sig.size and not ((sig >= 0) & (sig < len(SIGNALS))).all():
        raise GeometryError(f"{name}: signal indices must be integers in [0, {len(SIGNALS)}), got {sig.tolist()}")
    return sig.astype(np.int8)


def _lone_epoch(corrector: PriorProvider, sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray,
                pr_sigma: np.ndarray | None, cn0: np.ndarray | None, signal: np.ndarray | None) -> Trace:
    """One epoch as a trace, refusing to leave out what the checkpoint reads and the caller must supply.

    A lone epoch has no history: the network sees every satellite as just acquired with no residual
    change (as at a trace's first epoch); on the held-out test drives that costs 0.1 and 0.9 m of GSDC score
    against the whole trace, and leaving ``pr_sigma`` at 1 m another 2.4 and 4.2 m (``experiments/lone_epoch.py``).
    """
    inputs = getattr(getattr(corrector, "features", None), "inputs", ())
    if "pr_sigma" in inputs and pr_sigma is None:
        raise GeometryError(f"{getattr(corrector, 'path', None) or 'the checkpoint'}: reads each satellite's reported "
                            "pseudorange sigma; pass pr_sigma (S,) [m] (GnssLogger: ReceivedSvTimeUncertaintyNanos "
                            "* 1e-9 * c; a Trace's pr_sigma row)")
    return one_epoch_trace(sat_pos, pr, mask, pr_sigma=pr_sigma, signal=signal, cn0=cn0)


def _batch_priors(corrector: PriorProvider, trace: Trace, init_pos: np.ndarray, valid: np.ndarray,
                  cov_scale: float, sigma_floor_m: float) -> Priors:
    """One corrector call for every epoch of ``trace``, cleaned by the graph's own rule
    (:func:`fusion.estimate.graph.priors.clean_priors`). init_pos (E,3) ECEF, valid (E,) bool epochs to try."""
    E = trace.n_epochs
    init_pos, valid = np.asarray(init_pos, float), np.asarray(valid, bool)
    if init_pos.shape != (E, 3) or valid.shape != (E,):
        raise GeometryError(f"{trace.name}: init_pos must be ({E}, 3) and valid ({E},); got "
                            f"{init_pos.shape} and {valid.shape}")
    valid = valid & np.isfinite(init_pos).all(axis=1)
    mean, cov, ok = ask_provider(corrector, trace, np.where(valid[:, None], init_pos, 0.0), valid)
    return clean_priors(mean, cov, ok & valid, cov_scale, sigma_floor_m, what="cov_scale / sigma_floor_m")


def _epoch_prior(corrector: PriorProvider, trace: Trace, init_pos: np.ndarray, cov_scale: float,
                 sigma_floor_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A 1-epoch ``trace`` through :func:`_batch_priors`: (mean (3,), covariance used (3,3)), or GeometryError."""
    init_pos = np.asarray(init_pos, float)
    if init_pos.shape != (3,) or not np.isfinite(init_pos).all():
        raise GeometryError(f"init_pos must be a finite ECEF (3,) vector, got {init_pos!r}")
    mask = trace.mask[0]
    pri = _batch_priors(corrector, trace, init_pos[None], np.ones(1, bool), cov_scale, sigma_floor_m)
    if not pri.ok[0]:
        if pri.finite[0] and not pri.spd[0]:
            raise GeometryError(f"the learned covariance is not positive definite (smallest eigenvalue "
                                f"<= {PRIOR_MIN_EIG} m^2)")
        raise GeometryError(f"the learned corrector gave no estimate for this epoch ({int(np.sum(mask))} "
                            f"satellites; it needs >= 4 above its elevation mask at the initial position)")
    return pri.mean[0], pri.cov[0]


def learned_prior(corrector: PriorProvider, sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray,
                  init_pos: np.ndarray, *, pr_sigma: np.ndarray | None = None, cn0: np.ndarray | None = None,
                  signal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The learned position estimate for one epoch: (mean_ecef (3,), cov_ecef (3,3) symmetrised).

    Arguments as for :func:`learned_prior_factor`. Raises :class:`GeometryError` when the corrector declines
    the epoch (e.g. fewer than 4 satellites above its elevation mask at ``init_pos``), returns a covariance
    that is not positive definite (smallest eigenvalue <= ``fusion.estimate.graph.priors.PRIOR_MIN_EIG``, the
    graph's rule), or reads a ``pr_sigma`` not given.
    """
    trace = _lone_epoch(corrector, sat_pos, pr, mask, pr_sigma, cn0, signal)
    return _epoch_prior(corrector, trace, init_pos, 1.0, 0.0)


@dataclass(frozen=True)
class PriorNoise:
    """How a learned prior's covariance becomes its factor's noise model: ``cov_scale * cov +
    sigma_floor_m**2 * I``, wrapped in a robust loss (``robust``: "huber", "cauchy" or "none") on the
    Mahalanobis distance (``robust_k`` in sigmas). The defaults use the network's covariance as is."""

    cov_scale: float = 1.0
    sigma_floor_m: float = 0.0
    robust: str = "none"
    robust_k: float = 1.0

    @classmethod
    def of(cls, options: dict) -> PriorNoise:
        """From keyword options (any of the fields); an unknown name is a ``TypeError``, as Python's own."""
        unknown = sorted(set(options) - {f.name for f in fields(cls)})
        if unknown:
            raise TypeError(f"unexpected keyword argument(s) {', '.join(unknown)}")
        return cls(**options)


def learned_prior_factor(corrector: PriorProvider, sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray,
                         init_pos: np.ndarray, key: int, *, pr_sigma: np.ndarray | None = None,
                         cn0: np.ndarray | None = None, signal: np.ndarray | None = None, **noise
                         ) -> tuple[gtsam.PriorFactorPoint3, np.ndarray, np.ndarray]:
    """A ``PriorFactorPoint3`` on ``key`` at the DNN-corrected position of one epoch.

    corrector: a trained ``learned.infer.Corrector`` (or any position prior provider callable
        ``(trace, init_pos (E,3), valid (E,)) -> (mean (E,3), cov (E,3,3), valid (E,))``).
    sat_pos:   (S,3) satellite ECEF at transmit time [m] (unrotated; the corrector handles Sagnac).
    pr:        (S,) corrected pseudoranges [m] (satellite clock, iono, tropo removed).
    mask:      (S,) bool, which slots are real.
    init_pos:  (3,) ECEF initial guess [m] (e.g. WLS or the previous estimate; never the truth).
    key:       the GTSAM key of an ECEF ``Point3`` variable.
    pr_sigma:  (S,) the receiver's reported pseudorange sigma [m]; required when the checkpoint reads it
        (the shipped one does: it is most of the network's gain).
    cn0, signal: (S,) C/N0 [dB-Hz] (0 = unknown, the default) and signal names or
        ``fusion.trace.SIGNALS`` indices (default GPS_L1; slots of signals the network was not trained on are
        left out and lower its trust).

    A lone epoch has no history (residual change, arc age): the network reads it like a trace's first epoch.
    With a whole trace, :func:`learned_prior_factors` gives what the ``fused`` mode uses.

    noise: ``cov_scale``, ``sigma_floor_m``, ``robust``, ``robust_k`` (:class:`PriorNoise`): the covariance
        used is ``cov_scale * cov + sigma_floor_m**2 * I``, wrapped in a robust loss ("huber", "cauchy" or
        "none") on the Mahalanobis distance (``robust_k`` in sigmas). The defaults use the network's
        covariance as is; our own graph uses ``fusion.estimate.graph.config.GraphConfig``'s prior_cov_scale,
        prior_sigma_floor_m, prior_robust, prior_robust_k (4, 2 m, "cauchy", 1; tuning table in its
        docstring), which keep a confidently wrong output from dragging the solution.

    Returns ``(factor, mean_ecef (3,), cov_ecef (3,3))``, ``cov_ecef`` being the covariance in the
    factor's noise model. The receiver clock is estimated inside the corrector from the
    pseudoranges, so the factor involves the position only. Raises :class:`GeometryError` if the
    corrector cannot produce an estimate.
    """
    nm = PriorNoise.of(noise)
    trace = _lone_epoch(corrector, sat_pos, pr, mask, pr_sigma, cn0, signal)
    mean, cov = _epoch_prior(corrector, trace, init_pos, nm.cov_scale, nm.sigma_floor_m)
    return gtsam.PriorFactorPoint3(key, mean, prior_noise_model(cov, nm.robust, nm.robust_k)), mean, cov


def learned_pose_translation_factor(corrector: PriorProvider, sat_pos: np.ndarray, pr: np.ndarray,
                                    mask: np.ndarray, init_pos: np.ndarray, key: int, *,
                                    pr_sigma: np.ndarray | None = None, cn0: np.ndarray | None = None,
                                    signal: np.ndarray | None = None, **noise
                                    ) -> tuple[gtsam.PoseTranslationPrior3D, np.ndarray, np.ndarray]:
    """Like :func:`learned_prior_factor` (same options) for a ``Pose3`` variable whose translation is ECEF.

    ``PoseTranslationPrior3D``'s error is ``translation - measured`` in the *world* frame (checked
    in ``tests/learned/test_factor.py``), so the ECEF covariance is used as is, whatever the pose's rotation.
    """
    nm = PriorNoise.of(noise)
    trace = _lone_epoch(corrector, sat_pos, pr, mask, pr_sigma, cn0, signal)
    mean, cov = _epoch_prior(corrector, trace, init_pos, nm.cov_scale, nm.sigma_floor_m)
    return gtsam.PoseTranslationPrior3D(key, mean, prior_noise_model(cov, nm.robust, nm.robust_k)), mean, cov


def learned_prior_factors(corrector: PriorProvider, trace: Trace, init_pos: np.ndarray, valid: np.ndarray,
                          keys: list[int], on_pose: bool = False, *, cov_scale: float = 1.0,
                          sigma_floor_m: float = 0.0, robust: str = "none", robust_k: float = 1.0
                          ) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
    """Learned priors for every epoch of a trace in one batched corrector call.

    init_pos (E,3) ECEF guesses, valid (E,) bool epochs to try, keys: E GTSAM keys.
    on_pose: ``PoseTranslationPrior3D`` on ``Pose3`` keys instead of ``PriorFactorPoint3``.
    cov_scale, sigma_floor_m, robust, robust_k: as for :func:`learned_prior_factor`.
    Returns ``(factors, mean (E,3), cov (E,3,3), ok (E,))``, ``cov`` the covariances in the noise
    models; ``factors[k]`` is None where ``ok[k]`` is False (declined by the corrector, non-finite,
    or covariance not positive definite), and there ``mean[k]`` is 0 and ``cov[k]`` the identity.
    """
    if len(keys) != trace.n_epochs:
        raise GeometryError(f"{trace.name}: {trace.n_epochs} keys needed, got {len(keys)}")
    pri = _batch_priors(corrector, trace, init_pos, valid, cov_scale, sigma_floor_m)
    make = gtsam.PoseTranslationPrior3D if on_pose else gtsam.PriorFactorPoint3
    factors = [make(keys[k], pri.mean[k], prior_noise_model(pri.cov[k], robust, robust_k)) if pri.ok[k] else None
               for k in range(trace.n_epochs)]
    return factors, pri.mean, pri.cov, pri.ok


def learned_pseudorange_factors(corrector, trace: Trace, init_pos: np.ndarray, valid: np.ndarray,
                                pos_keys: list[int], clock_keys: list[int], *, default_sigma_m: float = 5.0,
                                robust: str = "huber", robust_k: float = 2.0,
                                sigma_power: float = 1.0) -> tuple[list[list], np.ndarray]:
    """GTSAM ``PseudorangeFactor`` per measurement, weighted by the per-satellite head.

    corrector: a ``learned.infer.Corrector`` (its :meth:`slot_noise` is asked at ``init_pos``).
    trace: the measurements (E epochs, S slots); init_pos (E,3) ECEF guesses (never the truth);
    valid (E,) bool epochs to ask; pos_keys / clock_keys: E keys of an ECEF ``Point3`` and of a receiver
    clock in seconds (``double``), as GTSAM's ``PseudorangeFactor`` expects.
    Each factor measures ``pr - bias`` with sigma from the head; slots the head has no opinion on (not
    asked, out of the training range, other signals) get ``default_sigma_m`` and no bias. The noise model is
    wrapped in ``robust`` at ``robust_k`` sigmas. ``sigma_power``: the head's multiplier raised to it
    (:func:`learned.infer.graph_sigma`; 1: the head as trained). The ``fused`` mode's graph takes
    ``GraphConfig.learned_sigma_power`` (4) beside a Cauchy loss at 1.5 and a constant-velocity model; in
    example 05's random walk with Huber at 2, 3 did worse than 1 (horizontal p95 21.2 against 18.3 m,
    ``examples/05_learned_pseudorange_factors.py --sigma-power 3``), so choose it for your own graph.
    Returns ``(factors per epoch (E lists), sigma (E,S))``, the sigma used per slot (NaN on padding).
    """
    E = trace.n_epochs
    if len(pos_keys) != E or len(clock_keys) != E:
        raise GeometryError(f"{trace.name}: {E} position and clock keys needed, got {len(pos_keys)} / {len(clock_keys)}")
    # a slot-noise source written before the power existed takes no sigma_power
    noise = corrector.slot_noise() if sigma_power == 1.0 else corrector.slot_noise(sigma_power=sigma_power)
    sigma, bias = noise(trace, np.asarray(init_pos, float), np.asarray(valid, bool))
    have = np.isfinite(sigma) & np.isfinite(bias)
    used = np.where(trace.mask, np.where(have, sigma, default_sigma_m), np.nan)
    pr = trace.pr - np.where(have, bias, 0.0)
    factors = [[gtsam.PseudorangeFactor(pos_keys[k], clock_keys[k], float(pr[k, s]), trace.sat_pos[k, s], 0.0,
                                        robust_model(robust, robust_k, gtsam.noiseModel.Isotropic.Sigma(1, float(used[k, s]))))
                for s in np.flatnonzero(trace.mask[k])] for k in range(E)]
    return factors, used
