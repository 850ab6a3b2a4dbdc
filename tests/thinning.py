"""A dual-frequency trace thinned to three satellites at some epochs, for tests of what too few satellites do."""
from __future__ import annotations

import dataclasses

import numpy as np

from fusion.trace import Trace


def three_satellites(trace: Trace, epochs, on_two: int = 1) -> Trace:
    """``trace`` with at most three satellites kept at each of ``epochs``: up to ``on_two`` of them with both their
    frequencies, the others with their one (so up to 3 + ``on_two`` pseudoranges of three directions)."""
    mask = trace.mask.copy()
    for k in epochs:
        ids, n = np.unique(trace.sat_id[k][trace.mask[k]], return_counts=True)
        keep = np.r_[ids[n == 2][:on_two], ids[n == 1][:3 - on_two]]
        mask[k] &= np.isin(trace.sat_id[k], keep)
    return dataclasses.replace(trace, mask=mask)
