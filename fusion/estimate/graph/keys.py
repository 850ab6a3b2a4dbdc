"""GTSAM keys of the fused graph's variables, named for what they key.

- ``pos_key(k)``: receiver position at epoch ``k``, ``Point3`` ECEF [m];
- ``clock_key(k)``: receiver clock bias at epoch ``k`` in *seconds* (GTSAM's ``PseudorangeFactor``
  multiplies it by c; our code carries the clock in metres and converts only at this boundary);
- ``vel_key(k)``: receiver velocity at epoch ``k``, ECEF [m/s] (constant-velocity motion);
- ``isb_key(comp, g)``: the (negated) inter-system bias [m] of signal group ``g`` in motion
  component ``comp``;
- ``drift_key(k)``: the receiver clock drift at epoch ``k`` (graphs with Doppler only), stored as the
  clock extrapolated :data:`DRIFT_HORIZON_S` ahead, ``c(k) + drift(k) * DRIFT_HORIZON_S`` [s]. GTSAM's
  C++ ``DopplerFactor`` takes the drift as ``(clock_b - clock_a) / dt`` of two clock keys, so with
  ``(c(k), d(k))`` and ``dt = DRIFT_HORIZON_S`` it sees exactly ``drift(k)``: the Doppler factor stays
  in C++ (a Python ``CustomFactor`` per satellite would be far slower) and the drift is still a state
  of its own, chained by a random walk (:mod:`fusion.estimate.graph.factors`);
- ``doppler_drift_key(k)``: the drift as epoch ``k``'s Doppler sees it, held as ``drift_key`` is (graphs whose
  log shows a drift that jumps from epoch to epoch, :mod:`fusion.estimate.graph.drift_noise`): the drift plus a
  white jump of that epoch, which the Doppler factors take and the clock does not integrate;
- ``disp_key(k)``: the receiver displacement ``x(k) - x(k-1)`` [m] (graphs with carrier phase only),
  on which the time-differenced carrier factor acts (see :func:`~fusion.estimate.graph.factors.tdcp_factor_uqq`);
- ``carrier_clock_key(k)``: the receiver clock as the carrier phase sees it [m], up to a constant per
  carrier chain. It is a state of its own, in metres, rather than ``c(k)``: a 2 cm carrier factor on
  the clocks in seconds has whitened coefficients ~1e10 next to ~50 on the displacement, and ISAM2's
  Cholesky then lost the displacement (an "indeterminant system" on simulated traces).
"""
from __future__ import annotations

import gtsam

#: signal groups per component are packed into one key index: 16 > len(SIGNALS)
ISB_STRIDE = 16

#: symbol character -> what it keys, for error messages
KEY_NAMES = {"x": "position", "c": "receiver clock", "v": "velocity", "i": "inter-system bias",
             "d": "receiver clock drift", "j": "receiver clock drift as the Doppler sees it",
             "u": "displacement since the previous epoch", "q": "carrier clock"}

#: the drift key holds the clock this far ahead [s]; see the module docstring
DRIFT_HORIZON_S = 1.0


def pos_key(k: int) -> int:
    """Key of the position at epoch ``k``."""
    return gtsam.symbol("x", k)


def clock_key(k: int) -> int:
    """Key of the receiver clock (seconds) at epoch ``k``."""
    return gtsam.symbol("c", k)


def vel_key(k: int) -> int:
    """Key of the velocity at epoch ``k`` (constant-velocity motion only)."""
    return gtsam.symbol("v", k)


def isb_key(comp: int, group: int) -> int:
    """Key of the (negated) inter-system bias [m] of signal ``group`` in motion component ``comp``."""
    return gtsam.symbol("i", ISB_STRIDE * comp + group)


def drift_key(k: int) -> int:
    """Key of the receiver clock drift at epoch ``k``, held as ``c(k) + drift(k) * DRIFT_HORIZON_S`` [s]."""
    return gtsam.symbol("d", k)


def doppler_drift_key(k: int) -> int:
    """Key of the drift as epoch ``k``'s Doppler sees it, held as :func:`drift_key` is [s]."""
    return gtsam.symbol("j", k)


def disp_key(k: int) -> int:
    """Key of the displacement x(k) - x(k-1) [m] (graphs with carrier phase only)."""
    return gtsam.symbol("u", k)


def carrier_clock_key(k: int) -> int:
    """Key of the carrier-phase clock at epoch ``k`` [m] (graphs with carrier phase only)."""
    return gtsam.symbol("q", k)
