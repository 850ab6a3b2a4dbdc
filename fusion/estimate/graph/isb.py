"""Inter-system bias states: which signal group each slot belongs to, where each group's bias is
introduced, its starting value, and reading the estimates back.

Every signal other than the reference (GPS L1 when present, else the first signal present) gets
one constant bias per motion component (a window without gaps), only with ``isb="window"`` and
only for groups that occur. GPS-only traces get no bias states at all.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.config import GraphConfig
from fusion.estimate.graph.keys import isb_key
from fusion.trace import SIGNALS, Trace


@dataclass
class IsbInputs:
    """E epochs, S slots, G signal groups. group (E,S) int: each slot's group (-1: reference clock);
    new (E,G) bool: epoch k is the first in its component to use group g (its bias key and prior
    are introduced there), or None without bias states; init_m (G,) starting bias per group [m];
    groups: the SIGNALS index of each group."""

    group: np.ndarray
    new: np.ndarray | None = None
    init_m: np.ndarray | None = None
    groups: tuple = ()


def isb_inputs(trace: Trace, sel: np.ndarray, comp: np.ndarray, init_clock_m: np.ndarray,
               resid: np.ndarray, cfg: GraphConfig) -> IsbInputs:
    """Signal groups, first-use epochs and initial values of the inter-system biases.

    sel (E,S) bool slots used; comp (E,) motion component; init_clock_m (E,) [m];
    resid (E,S) pseudorange minus range at the initial position (NaN where not selected).
    """
    out = IsbInputs(group=np.full(sel.shape, -1, np.int64))
    if cfg.isb == "none":
        return out
    if cfg.isb != "window":
        raise GeometryError(f"unknown isb model {cfg.isb!r}; choose window or none")
    if not cfg.isb_sigma_m > 0:
        raise GeometryError(f"GraphConfig: isb_sigma_m must be > 0, got {cfg.isb_sigma_m}")
    sig = np.asarray(trace.signal, np.int64)
    present = np.unique(sig[sel])
    if present.size <= 1:
        return out                                   # one signal: its clock is the receiver clock
    ref = 0 if 0 in present else int(present[0])     # SIGNALS[0] = GPS_L1
    out.groups = tuple(int(g) for g in present if g != ref)
    out.new = np.zeros((sel.shape[0], len(out.groups)), bool)
    out.init_m = np.zeros(len(out.groups))
    # bias residue per satellite: pseudorange residual minus the epoch's (reference) clock
    d = resid - init_clock_m[:, None]
    starts = np.r_[0, np.flatnonzero(np.diff(comp)) + 1]
    for g, sg in enumerate(out.groups):              # a handful of signal groups, not epochs
        in_g = sel & (sig == sg)
        out.group[in_g] = g
        used = in_g.any(axis=1)
        # first epoch of each component using this group: use count since the component start is 1
        cnt = np.cumsum(used)
        before = np.concatenate([[0], cnt[:-1]])[starts]
        out.new[:, g] = used & (cnt - before[comp] == 1)
        # one trace-wide starting value (the factors are linear in the bias, so LM needs no better)
        out.init_m[g] = np.nan_to_num(np.nanmedian(np.where(in_g, d, np.nan)))
    return out


def isb_label(signal: int, comp: int) -> str:
    """The key of an inter-system bias estimate: ``"<signal>@<component>"``, signal a SIGNALS index."""
    return f"{SIGNALS[signal]}@{int(comp)}"


def isb_estimates(values: gtsam.Values, inp) -> dict[str, float]:
    """Estimated inter-system biases [m] (pseudorange minus the reference-clock model), keyed
    ``"<signal>@<component>"``, for every bias state in ``values``; ``inp`` the graph's
    :class:`~fusion.estimate.graph.inputs.EpochInputs`."""
    out = {}
    isb = inp.isb
    if isb.new is None:
        return out
    for g, sg in enumerate(isb.groups):
        for c in np.unique(inp.comp[isb.new[:, g] & inp.keep]):
            key = isb_key(int(c), g)
            if values.exists(key):
                out[isb_label(sg, c)] = -float(values.atDouble(key))   # the key holds -ISB
    return out
