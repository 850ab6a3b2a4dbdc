"""What every mode takes and returns: the run options and a mode's result.

These sit below the estimators (which import them) and below the application layer (the mode
registry in :mod:`fusion.modes`, the CLI), so no estimator depends on the code that calls it.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from fusion.estimate.graph.config import GraphConfig


@dataclass
class RunOptions:
    """Settings shared by every mode of one run."""

    weights: Path | None = None          # DNN checkpoint; None = the weights shipped in learned/weights
    elev_mask_deg: float = 10.0
    device: str = "cpu"
    dnn_passes: int = 1                  # DNN applied iteratively, features recomputed each pass
    signals: tuple[str, ...] | None = ("GPS_L1",)   # None: the format's default (GPS L1 for GSDC
                                                  # files, every signal with ephemerides for raw logs)
    nav: tuple[Path, ...] = ()           # raw logs: broadcast navigation files (else the folder's)
    sp3: Path | None = None              # raw logs: precise orbits (+ clocks) instead of broadcast
    clk: Path | None = None              # raw logs: precise clocks (RINEX clock file) with sp3
    iono_free: bool = False              # raw logs: ionosphere-free combination of dual-frequency pairs
    wls_weighting: str = "elevation"
    wls_robust: bool | str = "exclude"   # fault detection and exclusion; False = plain (--wls-plain)
    # fused mode: which learned parts enter the graph (the report isolates what each adds)
    learned_prior: bool = True           # the network's position prior per epoch
    learned_sigmas: bool = True          # the per-satellite head's pseudorange sigma and bias
    learned_bias: bool = True            # ... its bias (off: the head's sigmas alone)
    learned_doppler: bool = True         # the Doppler head's pseudorange-rate sigmas (where the weights have one)
    dnn_output: str | None = None        # "wls" | "correction"; None: the checkpoint's
    # reported covariances follow each mode's windowed a-posteriori variance factor
    # (fusion.estimate.variance_factor); positions are the same either way
    sigma_calibration: bool = True
    # ... with each mode's own setting at the epochs carrier phase ties (variance_factor.CARRIER_DEFAULTS); False:
    # those epochs take the mode's general setting too
    carrier_sigma_calibration: bool = True
    # the fused graph's settings, Doppler / carrier / incremental switches included
    graph: GraphConfig = field(default_factory=GraphConfig)

    @property
    def use_doppler(self) -> bool:
        return self.graph.use_doppler

    @property
    def use_carrier(self) -> bool:
        return self.graph.use_carrier

    @property
    def incremental(self) -> bool:
        return self.graph.incremental

    @property
    def use_odometry(self) -> bool:
        return self.graph.use_odometry

    def with_absolute_paths(self) -> "RunOptions":
        """These options with every file they name (weights, navigation, SP3, clock) made absolute: a
        cluster's workers have working directories of their own."""
        absolute = lambda p: None if p is None else Path(p).absolute()  # noqa: E731
        return replace(self, weights=absolute(self.weights), nav=tuple(absolute(p) for p in self.nav),
                       sp3=absolute(self.sp3), clk=absolute(self.clk))


@dataclass
class ModeResult:
    """Output of one mode on one trace.

    pos:   (E, 3) ECEF [m], NaN rows where the epoch was not solved.
    valid: (E,) bool.
    cov:   (E, 3, 3) ECEF position covariance [m^2], or None when the mode gives none.
    info:  counts and diagnostics for the report (e.g. skipped epochs by reason).
    """

    pos: np.ndarray
    valid: np.ndarray
    cov: np.ndarray | None = None
    info: dict = field(default_factory=dict)
