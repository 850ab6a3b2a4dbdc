"""GTSAM's solver exceptions turned into our one-line errors, naming the epoch and variable."""
from __future__ import annotations

import re

import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.inputs import EpochInputs
from fusion.estimate.graph.keys import ISB_STRIDE, KEY_NAMES
from fusion.trace import Trace


def epoch_label(trace: Trace, k: int) -> str:
    return f"{trace.name}: epoch {k} (t_ms={int(trace.t_ms[k])})"


def geometry_error(trace: Trace, exc: Exception) -> GeometryError:
    """Turn GTSAM's indeterminant-system exception into our error, naming the epoch."""
    msg = str(exc)
    m = re.search(r"Symbol: ([xcviudq])(\d+)", msg)
    if m and m.group(1) == "i":
        idx = int(m.group(2))
        return GeometryError(f"{trace.name}: the graph cannot determine the inter-system bias of signal group "
                             f"{idx % ISB_STRIDE} in motion component {idx // ISB_STRIDE} (singular system)")
    if m:
        k = int(m.group(2))
        return GeometryError(f"{epoch_label(trace, k)}: the graph cannot determine the {KEY_NAMES[m.group(1)]} "
                             f"(singular system at {int(trace.mask[k].sum())} measured slots: too few satellites "
                             f"and no prior or motion link, or an input far off its model)")
    return GeometryError(f"{trace.name}: factor graph solve failed: {msg.splitlines()[0] if msg else repr(exc)}")


def check_determined(trace: Trace, inp: EpochInputs) -> None:
    """Raise :class:`GeometryError` naming the first epoch nothing can determine."""
    bad = np.flatnonzero(~inp.keep)
    if bad.size:
        k = int(bad[0])
        raise GeometryError(f"{epoch_label(trace, k)}: {int(inp.sel[k].sum())} usable pseudoranges, no "
                            f"position prior, and no motion link to an epoch with >= 4 satellites or a prior; "
                            f"its position is undetermined")
