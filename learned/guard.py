"""Out-of-distribution guard: how far to trust the network on an epoch it was not trained for.

Version-3 features (:func:`feature_guard`) are guarded per measurement and per feature: a feature the
training data never had present (C/N0 for the 2021 files) or a value outside its training range reads
as *missing* for that measurement; a constellation or signal never seen in training reads as *unknown*
(both learned with feature dropout); only a measurement whose own residual, residual change or arc age
leaves the training range is handed to the physical sigma model, and the epoch's trust falls with the
share of those. Version-2 checkpoints keep the rule below.

Training stores, per input channel, the range the training inputs spanned (quantiles 0.1 % and 99.9 % over
real slots, at the samples' WLS solutions; :func:`input_ranges`). At inference a slot is *out of range* when
any channel leaves that range widened by :data:`MARGIN` of its width; an epoch's trust is 1 while at most
:data:`SHARE_FULL` of its slots are out of range, falling linearly to 0 at :data:`SHARE_NONE`
(:func:`trust`); satellites of signals the network was not trained on count as out of range. The modes shrink the learned correction by the trust (toward the guess: plain WLS for
``dnn``) and fall back to the default pseudorange sigma on out-of-range slots (``fused``): a phone, city
or firmware the network never met gets the non-learned answer instead of a confident wrong one.
"""
from __future__ import annotations

import numpy as np

MARGIN = 0.1
SHARE_FULL, SHARE_NONE = 0.1, 0.5
_QUANTILES = (0.001, 0.999)
#: Channels that are bounded by construction (line-of-sight components) are not checked.
_SKIP = slice(1, 4)


def input_ranges(x: torch.Tensor, mask: torch.Tensor) -> dict:
    """Per-channel [lo, hi] of training inputs ``x`` (N,S,F) over real slots ``mask`` (N,S)."""
    import torch  # training only
    v = x[mask].double()
    if v.shape[0] > 200_000:      # quantile has a size limit; an even subsample is as good for ranges
        v = v[torch.linspace(0, v.shape[0] - 1, 200_000).long()]
    q = torch.quantile(v, torch.tensor(_QUANTILES, dtype=v.dtype, device=v.device), dim=0)
    return {"lo": [float(a) for a in q[0]], "hi": [float(a) for a in q[1]]}


def widened_ranges(base: dict | None, new: dict | None) -> dict | None:
    """The guard's ranges covering both a base network's training inputs and those it was fine-tuned on
    (an adaptation's, or the real data after pre-training)."""
    if not base or not new:
        return base or new
    return {"lo": [min(a, b) for a, b in zip(base["lo"], new["lo"])],
            "hi": [max(a, b) for a, b in zip(base["hi"], new["hi"])]}


def slot_out_of_range(x: np.ndarray, mask: np.ndarray, ranges: dict | None) -> np.ndarray:
    """(N,S) bool: real slots of inputs ``x`` (N,S,F) with a channel outside the widened training range."""
    if not ranges:
        return np.zeros(mask.shape, bool)
    lo, hi = np.asarray(ranges["lo"]), np.asarray(ranges["hi"])
    pad = MARGIN * (hi - lo)
    out = (x < lo - pad) | (x > hi + pad)
    out[..., _SKIP] = False
    return out.any(-1) & mask


def _widened(ranges: dict) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.asarray(ranges["lo"], float), np.asarray(ranges["hi"], float)
    pad = MARGIN * (hi - lo)
    return lo - pad, hi + pad


def feature_guard(x: np.ndarray, mask: np.ndarray, ranges: dict | None, cfg) -> tuple[dict, np.ndarray, dict]:
    """Per-measurement, per-feature guard of version-3 inputs ``x`` (N,S,F) on real slots ``mask`` (N,S).

    Returns ``missing`` (group -> (N,S) bool: read that group as missing / unknown there, for
    :func:`learned.features.context_channels`), ``core`` (N,S) bool (the slot's own residual, residual
    change or arc age is outside the training range: handed to the physical model) and counts by reason
    (``meas_signal_read_as_unknown``: the measurements its signal one-hot reads as an unknown signal).
    """
    from learned.features import BOUNDED_GROUPS, CATEGORY_GROUPS, FLAG_CHANNEL, OPTIONAL_GROUPS
    missing, counts = {}, {}
    if not ranges:
        return missing, np.zeros(mask.shape, bool), counts
    lo, hi = _widened(ranges)
    seen = np.asarray(ranges["hi"], float) >= 0.5
    sl = cfg.slices()
    for g in (k for k in OPTIONAL_GROUPS if k in sl):
        a = sl[g].start
        flag = a + FLAG_CHANNEL[g]
        present = mask & (x[..., flag] > 0.5)
        if not seen[flag]:
            drop = present
            counts[f"meas_{g}_unseen_in_training"] = int(drop.sum())
        elif g in BOUNDED_GROUPS:
            continue
        else:
            drop = present & ((x[..., a] < lo[a]) | (x[..., a] > hi[a]))
            counts[f"meas_{g}_out_of_range"] = int(drop.sum())
        missing[g] = drop
    for g in (k for k in CATEGORY_GROUPS if k in sl):
        cols = np.arange(sl[g].start, sl[g].stop - 1)          # the last one is "unknown" itself
        unseen = mask & (x[..., cols[~seen[cols]]] > 0.5).any(-1)
        missing[g] = unseen
        counts[f"meas_{g}_unseen_in_training"] = int(unseen.sum())
        # those and the ones the network's one-hot has no column for (signals newer than it) alike
        counts[f"meas_{g}_read_as_unknown"] = int((unseen | (mask & (x[..., sl[g].stop - 1] > 0.5))).sum())
    core_idx = [0] + [sl[g].start for g in ("dres", "arc") if g in sl]
    v = x[..., core_idx]
    core = mask & ((v < lo[core_idx]) | (v > hi[core_idx])).any(-1)
    counts["meas_out_of_range"] = int(core.sum())
    return missing, core, {k: v for k, v in counts.items() if v}


def trust(out_of_range: np.ndarray, mask: np.ndarray, unseen: np.ndarray | None = None) -> np.ndarray:
    """(N,) trust in [0, 1] from the share of out-of-range slots (N,S) among real slots (N,S).

    unseen: (N,) satellites of the epoch the network cannot read (signals it was not trained on),
    counted as out of range: a correction from a GPS-only subset must not override a solution that
    used every constellation.
    """
    extra = np.zeros(mask.shape[0]) if unseen is None else np.asarray(unseen, float)
    share = (out_of_range.sum(1) + extra) / np.maximum(mask.sum(1) + extra, 1)
    return np.clip((SHARE_NONE - share) / (SHARE_NONE - SHARE_FULL), 0.0, 1.0)
