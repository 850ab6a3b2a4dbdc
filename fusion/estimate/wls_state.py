"""What the WLS stages share: frozen settings (:class:`WlsSettings`) and the state of one batched fit
(:class:`FitState`).

Every stage of :mod:`fusion.estimate.wls` (coarse fix, mask, fine fit, fault exclusion in
:mod:`fusion.estimate.raim` and :mod:`fusion.estimate.neighbour_fde`, Huber IRLS) takes a
:class:`FitState` and returns a new one, so the per-epoch arrays travel together instead of as a dozen
loose parameters. The arrays a stage does not change are shared between the old and the new state
(never written in place), except ``n_iter`` and ``dropped``: they are the whole fit's counters, shared
on purpose so that every stage (a trial pass included) adds to them.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from fusion.errors import DataError
from fusion.estimate.lsq import gauss_newton

#: goGPS default a-priori code standard deviation (``STD_CODE``) [m].
SIGMA0_M = 3.0
WEIGHTINGS = ("elevation", "uncertainty", "none")
ROBUST_MODES = ("none", "exclude", "huber")
M_ESTIMATORS = ("huber", "cauchy")


@dataclass(frozen=True)
class WlsSettings:
    """Options of one WLS solve (:func:`fusion.estimate.wls.solve_wls_arrays` documents each stage).

    elev_mask_deg:  satellites below this elevation at the coarse fix are dropped [deg].
    weighting:      a-priori sigmas: ``"elevation"`` (``sigma0 / sin(el)``), ``"uncertainty"`` (the
                    phone's reported sigma) or ``"none"`` (``sigma0`` everywhere).
    robust:         ``"none"`` (plain WLS), ``"exclude"`` (fault detection and exclusion) or ``"huber"``
                    (Huber IRLS); ``False``/``None`` and ``True`` are accepted for ``"none"`` and
                    ``"exclude"`` and stored as those names.
    max_iter:       Gauss-Newton iterations per stage (>= 1).
    max_cond:       largest condition number of the unit-diagonal normal matrix.
    max_exclusions: most satellites fault exclusion removes from one epoch (>= 0).
    huber_k:        Huber threshold on standardised residuals.
    sigma0:         a-priori code sigma of the ``"elevation"`` and ``"none"`` weightings [m].
    cov_scale:      ``"posterior"`` (a-posteriori variance factor, floored at 1) or ``"prior"``.
    tol_m:          Gauss-Newton step tolerance of the fine stage [m].
    test_scale:     variance factor of the a-priori sigmas for the fault test: a number, or
                    ``"trace"`` to estimate it from the batch's own residuals.
    exclude_above_m, max_dop_growth: an exclusion whose removed residuals are all below
                    ``exclude_above_m`` [m] (at the re-solved position) and that raises the weighted
                    position DOP by more than the factor ``max_dop_growth`` is undone: the epoch is
                    flagged and down-weighted by Huber IRLS instead
                    (:func:`fusion.estimate.raim.costly_exclusions`). ``inf``: every identified fault
                    is excluded (the behaviour before the guard).
    gross_dop_growth: any exclusion (a gross residual too) that raises the weighted position DOP by more
                    than this factor is undone likewise: Huber bounds a gross fault's pull, a lost
                    satellite in a weak geometry costs more (``inf``: never).
    neighbour_weak: the neighbour check (:mod:`fusion.estimate.neighbour_fde`) also reconsiders epochs
                    that passed the test with few satellites; ``False``: only the undecided (flagged) ones.
    irls_scale:     the scale the M-estimator standardises residuals with: ``"prior"`` (the a-priori
                    sigmas) or ``"trace"`` (times the square root of the test's variance factor).
    m_estimator:    weight function of the IRLS: ``"huber"`` (``min(1, k/|z|)``) or ``"cauchy"``
                    (``1 / (1 + (z/k)^2)``), ``k = huber_k``.
    """

    elev_mask_deg: float = 10.0
    weighting: str = "elevation"
    robust: bool | str | None = "none"
    max_iter: int = 10
    max_cond: float = 1e7
    max_exclusions: int = 3
    huber_k: float = 1.5
    sigma0: float = SIGMA0_M
    cov_scale: str = "posterior"
    tol_m: float = 1e-4
    test_scale: float | str = 1.0
    exclude_above_m: float = float("inf")
    max_dop_growth: float = 1.0
    gross_dop_growth: float = float("inf")
    neighbour_weak: bool = True
    irls_scale: str = "prior"
    m_estimator: str = "huber"
    irls_reported: bool = False

    def __post_init__(self) -> None:
        if self.weighting not in WEIGHTINGS:
            raise DataError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        object.__setattr__(self, "robust", _robust_mode(self.robust))
        if self.cov_scale not in ("posterior", "prior"):
            raise DataError(f"cov_scale must be 'posterior' or 'prior', got {self.cov_scale!r}")
        if self.max_iter < 1:
            raise DataError(f"max_iter must be >= 1, got {self.max_iter}")
        if self.max_exclusions < 0:
            raise DataError(f"max_exclusions must be >= 0, got {self.max_exclusions}")
        if self.irls_scale not in ("prior", "trace") or self.m_estimator not in M_ESTIMATORS:
            raise DataError(f"irls_scale must be 'prior' or 'trace' and m_estimator one of {M_ESTIMATORS}, got "
                            f"{self.irls_scale!r}, {self.m_estimator!r}")
        if not self.exclude_above_m > 0 or not self.max_dop_growth >= 1.0 or not self.gross_dop_growth >= 1.0:
            raise DataError(f"exclude_above_m must be > 0, max_dop_growth and gross_dop_growth >= 1, got "
                            f"{self.exclude_above_m}, {self.max_dop_growth}, {self.gross_dop_growth}")

    def replace(self, **options) -> WlsSettings:
        """A copy with ``options`` changed; an unknown option name is a :class:`DataError`."""
        unknown = sorted(set(options) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise DataError(f"unknown WLS option(s) {', '.join(unknown)}")
        return dataclasses.replace(self, **options) if options else self


def _robust_mode(robust) -> str:
    if robust is False or robust is None or robust == "none":
        return "none"
    if robust is True or robust == "exclude":
        return "exclude"
    if robust == "huber":
        return "huber"
    raise DataError(f"robust must be False, True, 'exclude' or 'huber', got {robust!r}")


@dataclass
class FitState:
    """A batched snapshot fit in progress. ``E`` epochs, ``S`` satellite slots.

    sat_pos:    (E, S, 3) transmit-time satellite ECEF [m], 0 on unusable slots.
    pr:         (E, S)    corrected pseudoranges [m], 0 on unusable slots.
    real:       (E, S)    bool, usable slots (real, finite inputs, usable sigma).
    w_prior:    (E, S)    a-priori weights ``1 / sigma^2`` [1/m^2], 0 below the mask and on failed epochs.
    used:       (E, S)    bool, slots in the current fit (above the mask and not excluded).
    x:          (E, 4)    state ``[x, y, z, clock]`` (ECEF [m], receiver clock c*dt [m]).
    w_fit:      (E, S)    weights of the current solution: ``w_prior`` on used slots, less after Huber IRLS.
    conv:       (E,)      bool, the last Gauss-Newton run of the epoch converged.
    bad:        (E,)      bool, an ill-conditioned normal matrix was met.
    runaway:    (E,)      bool, Gauss-Newton ran away (state reset to 0).
    flagged:    (E,)      bool, the fault test fails and no allowed exclusion repairs it.
    n_excluded: (E,)      int, measurements excluded by fault detection.
    n_iter:     (E,)      int, Gauss-Newton iterations spent (all stages; shared counter).
    dropped:    slot counts by reason (shared counter, see :class:`fusion.estimate.wls.WlsResult`).
    """

    sat_pos: np.ndarray
    pr: np.ndarray
    real: np.ndarray
    w_prior: np.ndarray
    used: np.ndarray
    x: np.ndarray
    w_fit: np.ndarray
    conv: np.ndarray
    bad: np.ndarray
    runaway: np.ndarray
    flagged: np.ndarray
    n_excluded: np.ndarray
    n_iter: np.ndarray
    dropped: dict[str, int] = field(default_factory=dict)

    @property
    def weights(self) -> np.ndarray:
        """(E, S) the a-priori weights on the used slots, 0 elsewhere."""
        return np.where(self.used, self.w_prior, 0.0)

    def replace(self, **changes) -> FitState:
        return dataclasses.replace(self, **changes)

    def solve(self, active: np.ndarray, w: np.ndarray, max_iter: int, tol: float, max_cond: float) -> FitState:
        """Gauss-Newton from the current state on the ``active`` (E,) epochs with weights ``w`` (E, S).

        The active epochs' ``conv`` is replaced by this run's; ``bad`` and ``runaway`` accumulate.
        """
        x, c2, b2, r2 = gauss_newton(self.sat_pos, self.pr, w, self.x.copy(), active, max_iter, tol, max_cond,
                                     self.n_iter)
        return self.replace(x=x, conv=np.where(active, c2, self.conv), bad=self.bad | (active & b2),
                            runaway=self.runaway | (active & r2))
