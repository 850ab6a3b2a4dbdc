"""What every mode takes and returns: the run options and a mode's result.

These sit below the estimators (which import them) and below the application layer (the mode
registry in :mod:`fusion.modes`, the CLI), so no estimator depends on the code that calls it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class RunOptions:
    """Settings shared by every mode of one run."""

    weights: Path | None = None          # DNN checkpoint; None = the weights shipped in learned/weights
    elev_mask_deg: float = 10.0
    device: str = "cpu"
    dnn_passes: int = 1                  # DNN applied iteratively, features recomputed each pass
    incremental: bool = False            # fused modes: ISAM2 / fixed-lag instead of batch LM
    signals: tuple[str, ...] | None = ("GPS_L1",)   # None: the format's default (GPS L1 for GSDC
                                                  # files, every signal with ephemerides for raw logs)
    nav: tuple[Path, ...] = ()           # raw logs: broadcast navigation files (else the folder's)
    sp3: Path | None = None              # raw logs: precise orbits (+ clocks) instead of broadcast
    clk: Path | None = None              # raw logs: precise clocks (RINEX clock file) with sp3
    wls_weighting: str = "elevation"
    wls_robust: bool | str = "exclude"   # fault detection and exclusion; False = plain (--wls-plain)
    # fused mode: which learned parts enter the graph (the report isolates what each adds)
    learned_prior: bool = True           # the network's position prior per epoch
    learned_sigmas: bool = True          # the per-satellite head's pseudorange sigma and bias
    dnn_output: str | None = None        # "wls" | "correction"; None: the checkpoint's
    # fused modes: use the trace's Doppler / carrier phase where it has them (no effect otherwise)
    use_doppler: bool = True
    use_carrier: bool = True
    use_odometry: bool = False           # fused modes: the trace's vehicle odometry (smartLoc), off by default


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
