"""GTSAM keys of the fused graph's variables, named for what they key.

- ``pos_key(k)``: receiver position at epoch ``k``, ``Point3`` ECEF [m];
- ``clock_key(k)``: receiver clock bias at epoch ``k`` in *seconds* (GTSAM's ``PseudorangeFactor``
  multiplies it by c; our code carries the clock in metres and converts only at this boundary);
- ``vel_key(k)``: receiver velocity at epoch ``k``, ECEF [m/s] (constant-velocity motion);
- ``isb_key(comp, g)``: the (negated) inter-system bias [m] of signal group ``g`` in motion
  component ``comp``.
"""
from __future__ import annotations

import gtsam

#: signal groups per component are packed into one key index: 16 > len(SIGNALS)
ISB_STRIDE = 16

#: symbol character -> what it keys, for error messages
KEY_NAMES = {"x": "position", "c": "receiver clock", "v": "velocity", "i": "inter-system bias"}


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
