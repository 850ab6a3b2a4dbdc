"""Training samples: per-epoch (sat_pos, pr, mask, truth) gathered from simulated and real traces.

Only epochs with truth are kept. Slots are masked with the same elevation mask WLS applies (default 10 deg),
evaluated at the *truth* for training (the guess is not known until augmentation draws it), so the network
sees the satellite sets it will see at inference; epochs left with < 4 satellites are dropped and counted.
Real data is split by trace upstream (whole phone-traces are train or test); validation is a random subset of
the training epochs (:func:`split_random`) or of contiguous blocks of them (:func:`split_blocks`; neighbouring
1 Hz epochs share multipath and geometry, so a random split validates on near-copies of training epochs).

Each sample also carries the WLS position of *its own measurements* (``wls``, no truth involved: the
same :func:`learned.context.context_wls` the corrector computes its context from, so training WLS is inference WLS),
computed once here, so training can draw
initial guesses from the distribution the network meets at inference (:mod:`learned.augment`).
With ``with_graph`` it also carries the solution of the factor graph without the learned prior
(``graph``: :func:`fusion.estimate.graph.fuse.fuse` with no provider, i.e. the ``fused-nodnn`` mode, measurements only),
solved once per trace: the point where the fused mode asks the network.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusion.errors import DataError, GnssfuseError
from fusion.estimate.graph.fuse import fuse
from fusion.estimate.variance_factor import centred_sums
from fusion.geometry import line_of_sight
from fusion.prepare.load import find_traces, load_trace
from fusion.prepare.raw_load import RawSources
from fusion.modes import solve_initial
from fusion.run_types import RunOptions
from fusion.sim.simulate import SimConfig, simulate_dataset
from fusion.trace import Trace
from learned.context import CONTEXT_KEYS, context_wls, slot_context
from learned.features import compact_slots, elevation_mask
from learned.toy import toy_dataset

#: Held-out traces that must never be trained on (test of the DNN, and of the fused pipeline).
FORBIDDEN_TRACES = ("2021-04-28-US-MTV-1/Pixel4", "2021-04-28-US-MTV-1/Pixel5", "2021-04-28-US-SJC-1")


@dataclass
class Samples:
    """sat_pos (N,S,3), pr (N,S), mask (N,S) bool, truth (N,3) ECEF, trace (N,) index into ``names``.

    wls:  (N,3) ECEF WLS position from the epoch's own measurements (NaN where WLS failed), or None.
    real: (N,) bool, True for samples from real (phone) traces, or None (all simulated).
    clock: (N,) the simulator's TRUE receiver clock [m], or None. Experiment only (the paper's leaky
        protocol, ``FeatureConfig(clock="given")``); never filled from phone data.
    graph: (N,3) ECEF no-prior factor-graph (fused-nodnn) position of the sample's trace (NaN where the
        graph left the epoch unsolved), or None.
    ctx: per-slot context (:mod:`learned.context`), (N,S) arrays keyed by ``CONTEXT_KEYS``, or None.
    pr_fast: (N,S) the part of each pseudorange's error at the truth that a short window along its arc averages
        away (:func:`fast_error`; 0 on padding), or None. Training labels only, never a model input.
    """

    sat_pos: np.ndarray
    pr: np.ndarray
    mask: np.ndarray
    truth: np.ndarray
    trace: np.ndarray
    names: list[str]
    skipped: dict[str, int] = field(default_factory=dict)
    wls: np.ndarray | None = None
    real: np.ndarray | None = None
    clock: np.ndarray | None = None
    graph: np.ndarray | None = None
    ctx: dict[str, np.ndarray] | None = None
    pr_fast: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.pr.shape[0])

    def wls_or_nan(self) -> np.ndarray:
        """(N,3) WLS positions, all-NaN when none were computed."""
        return np.full((len(self), 3), np.nan) if self.wls is None else self.wls

    def graph_or_nan(self) -> np.ndarray:
        """(N,3) graph positions, all-NaN when none were computed."""
        return np.full((len(self), 3), np.nan) if self.graph is None else self.graph

    def real_or_false(self) -> np.ndarray:
        return np.zeros(len(self), bool) if self.real is None else self.real

    def subset(self, idx: np.ndarray) -> "Samples":
        return Samples(self.sat_pos[idx], self.pr[idx], self.mask[idx], self.truth[idx], self.trace[idx],
                       list(self.names), dict(self.skipped),
                       None if self.wls is None else self.wls[idx], None if self.real is None else self.real[idx],
                       None if self.clock is None else self.clock[idx],
                       None if self.graph is None else self.graph[idx],
                       None if self.ctx is None else {k: v[idx] for k, v in self.ctx.items()},
                       None if self.pr_fast is None else self.pr_fast[idx])


def samples_from_trace(trace: Trace, elev_mask_deg: float = 10.0, index: int = 0, *, real: bool = False,
                       with_wls: bool = True, clock: np.ndarray | None = None, with_graph: bool = False,
                       slow_window_s: float = 0.0) -> Samples:
    """Epochs of one trace with finite truth and >= 4 satellites above the mask (at the truth).

    ``with_wls``: also solve WLS on the whole trace (:func:`learned.context.context_wls`, no truth), keep each
    sample's position and the per-slot context; ``real`` tags the samples as phone data.
    ``clock``: (E,) true receiver clock of a simulated trace, kept per sample (experiment only).
    ``with_graph``: also solve the no-prior factor graph on the whole trace (:func:`graph_positions`);
    samples without a graph position (unsolved epoch, or a trace the graph cannot solve) are counted in
    ``skipped["graph_invalid"]`` and keep NaN there.
    ``slow_window_s`` > 0: also keep each pseudorange's fast error part (:func:`fast_error` over that window) as
    ``pr_fast``, so that training can target the lasting part alone.
    """
    if trace.truth is None:
        raise DataError(f"{trace.name}: no ground truth, cannot be used for training")
    ok = np.isfinite(trace.truth).all(1)
    skipped = {"no_truth": int((~ok).sum())}
    idx = np.flatnonzero(ok)
    truth = trace.truth[idx]
    mask = elevation_mask(trace.sat_pos[idx], trace.mask[idx], truth, elev_mask_deg)
    enough = mask.sum(1) >= 4
    skipped["lt4_sats"] = int((~enough).sum())
    idx, mask, truth = idx[enough], mask[enough], truth[enough]
    w = context_wls(trace, elev_mask_deg) if (with_wls or with_graph) else None
    ctx = slot_context(trace, w, elev_mask_deg).as_dict() if w is not None else None
    # Real slots first, padding trimmed; padded slots zeroed so no stale measurement lingers there.
    extra = [ctx[k][idx] for k in CONTEXT_KEYS] if ctx is not None else []
    fast = fast_error(trace, slow_window_s)[idx] if slow_window_s > 0 else None
    sat_pos, pr, mask, *extra = compact_slots(trace.sat_pos[idx], trace.pr[idx], mask, *extra,
                                              *([] if fast is None else [fast]))
    if fast is not None:
        fast = np.where(mask, np.nan_to_num(extra.pop()), 0.0)
    sat_pos, pr = sat_pos * mask[..., None], pr * mask
    if ctx is not None:
        # every signal's pseudoranges on the reference signal's clock (learned.context: ``isb``)
        pr = pr - np.where(mask, extra[CONTEXT_KEYS.index("isb")], 0.0)
    ctx = None if ctx is None else {k: np.where(mask, v, np.asarray(1.0 if k == "pr_sigma" else 0).astype(v.dtype))
                                    for k, v in zip(CONTEXT_KEYS, extra)}
    wls = graph = None
    if with_wls:
        wls = np.where(w.valid[idx, None], w.pos[idx], np.nan)
        skipped["wls_invalid"] = int((~np.isfinite(wls).all(1)).sum())
    if with_graph:
        opts = RunOptions(elev_mask_deg=elev_mask_deg)       # the pipeline's own WLS starts the graph
        graph = graph_positions(trace, solve_initial(trace, opts), opts)[idx]
        skipped["graph_invalid"] = int((~np.isfinite(graph).all(1)).sum())
    if clock is not None and np.shape(clock) != (trace.n_epochs,):
        raise DataError(f"{trace.name}: clock must have shape ({trace.n_epochs},), got {np.shape(clock)}")
    return Samples(sat_pos, pr, mask, truth, np.full(len(idx), index), [trace.name], skipped, wls,
                   np.full(len(idx), bool(real)), None if clock is None else np.asarray(clock, float)[idx], graph,
                   ctx, fast)


def fast_error(trace: Trace, window_s: float) -> np.ndarray:
    """(E,S) each pseudorange's error at the truth minus its mean over the centred ``window_s`` along its
    satellite and signal (NaN where the slot or the truth is missing). The error is taken after the epoch's
    median (the receiver clock, and any bias all slots share); what is left after the window mean is what a
    smoother averages away, and the mean, what it cannot: multipath and reflections that last."""
    ok = trace.mask & np.isfinite(trace.truth).all(1)[:, None] if trace.truth is not None else None
    out = np.full(trace.pr.shape, np.nan)
    if ok is None or not ok.any():
        return out
    rng, _ = line_of_sight(trace.sat_pos, np.nan_to_num(trace.truth))
    r = np.where(ok, trace.pr - rng, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)            # epochs without a slot: all-NaN rows
        e = r - np.nanmedian(r, axis=1, keepdims=True)
    ii, ss = np.nonzero(ok & np.isfinite(e))
    t = trace.t_ms[ii] / 1000.0
    arc = np.unique((trace.sat_id[ii, ss].astype(np.int64) << 8) + trace.signal[ii, ss].astype(np.int64),
                    return_inverse=True)[1]
    # one sorted axis: arcs laid end to end, far enough apart that no window reaches the next
    key = arc * (np.ptp(t) + 2.0 * window_s + 1.0) + (t - t.min())
    order = np.argsort(key, kind="stable")
    k, v = key[order], e[ii, ss][order]
    fast = np.empty_like(v)
    fast[order] = v - centred_sums(k, v, window_s) / centred_sums(k, np.ones_like(v), window_s)
    out[ii, ss] = fast
    return out


def graph_positions(trace: Trace, wls, opts=None) -> np.ndarray:
    """(E,3) ECEF positions of the factor graph without the learned prior (the ``fused-nodnn`` mode at
    the GraphConfig defaults, fed the trace's WLS as the pipeline does), NaN where unsolved.

    opts: the ``fusion.run_types.RunOptions`` ``wls`` was solved with (None: the defaults).

    Uses the measurements only (``fuse`` never reads ``trace.truth``). A trace the graph cannot solve
    at all (a :class:`~fusion.errors.GnssfuseError`) gives all-NaN rows: those samples fall back to
    other guess sources instead of stopping a training run.
    """
    try:
        res = fuse(trace, wls, opts or RunOptions(), provider=None, want_cov=False)
    except GnssfuseError:
        return np.full((trace.n_epochs, 3), np.nan)
    return np.where(res.valid[:, None], res.pos, np.nan)


def concat_samples(parts: list[Samples]) -> Samples:
    """Concatenate, padding slots to the widest part; trace indices are renumbered."""
    if not parts:
        raise DataError("no training samples: every source was empty")
    S = max(p.mask.shape[1] for p in parts)

    def pad(a: np.ndarray) -> np.ndarray:
        w = [(0, 0), (0, S - a.shape[1])] + [(0, 0)] * (a.ndim - 2)
        return np.pad(a, w)

    names, trace, offset, skipped = [], [], 0, {}
    for p in parts:
        names += p.names
        trace.append(p.trace + offset)
        offset += len(p.names)
        for k, v in p.skipped.items():
            skipped[k] = skipped.get(k, 0) + v
    wls = None if all(p.wls is None for p in parts) else np.concatenate([p.wls_or_nan() for p in parts])
    real = None if all(p.real is None for p in parts) else np.concatenate([p.real_or_false() for p in parts])
    # A true clock only when every part has one: a partial array would silently mix in NaN clocks.
    clock = np.concatenate([p.clock for p in parts]) if all(p.clock is not None for p in parts) else None
    graph = None if all(p.graph is None for p in parts) else np.concatenate([p.graph_or_nan() for p in parts])
    # Context only when every part has it (a model reading it cannot train on parts without it).
    ctx = None if any(p.ctx is None for p in parts) else {
        k: np.concatenate([np.pad(p.ctx[k], [(0, 0), (0, S - p.mask.shape[1])], constant_values=float(k == "pr_sigma"))
                           for p in parts]) for k in CONTEXT_KEYS}
    # parts without the fast part (toy or simulated batches) are all lasting error: zero
    fast = None if all(p.pr_fast is None for p in parts) else np.concatenate(
        [pad(np.zeros(p.pr.shape) if p.pr_fast is None else p.pr_fast) for p in parts])
    return Samples(np.concatenate([pad(p.sat_pos) for p in parts]), np.concatenate([pad(p.pr) for p in parts]),
                   np.concatenate([pad(p.mask) for p in parts]), np.concatenate([p.truth for p in parts]),
                   np.concatenate(trace), names, skipped, wls, real, clock, graph, ctx, fast)


def split_random(samples: Samples, val_frac: float, rng: np.random.Generator) -> tuple[Samples, Samples]:
    """Random epochs of the training traces for validation (paper's protocol)."""
    n = len(samples)
    perm = rng.permutation(n)
    n_val = int(round(val_frac * n)) if n > 1 else 0
    return samples.subset(np.sort(perm[n_val:])), samples.subset(np.sort(perm[:n_val]))


def split_blocks(samples: Samples, val_frac: float, rng: np.random.Generator,
                 block: int = 60) -> tuple[Samples, Samples]:
    """Validation = random whole blocks of ``block`` consecutive samples of one trace (about ``val_frac``
    of the samples), so validation epochs are not next-second neighbours of training epochs."""
    n = len(samples)
    if n <= 1 or val_frac <= 0:
        return split_random(samples, val_frac, rng)
    # Block id: consecutive samples of the same trace, ``block`` at a time (samples are in trace order).
    pos_in_trace = np.arange(n) - np.searchsorted(samples.trace, samples.trace, side="left")
    key = samples.trace.astype(np.int64) * (n + 1) + pos_in_trace // block
    blocks, bid = np.unique(key, return_inverse=True)
    perm = rng.permutation(len(blocks))
    sizes = np.bincount(bid)[perm]
    n_blocks = int(np.argmin(np.abs(np.cumsum(sizes) - val_frac * n)) + 1)   # closest to val_frac * n
    is_val = np.isin(bid, perm[:min(n_blocks, len(blocks) - 1)])
    return samples.subset(np.flatnonzero(~is_val)), samples.subset(np.flatnonzero(is_val))


def split_traces(samples: Samples, val_frac: float, rng: np.random.Generator) -> tuple[Samples, Samples]:
    """Validation = whole traces (about ``val_frac`` of them, at least one when there are two or more), so
    that the best epoch is the one that generalises to a drive the network has not seen."""
    have = np.unique(samples.trace)          # a trace every epoch of which was dropped cannot validate
    if len(have) < 2 or val_frac <= 0:
        return split_blocks(samples, val_frac, rng)
    val = rng.permutation(have)[:max(1, int(round(val_frac * len(have))))]
    is_val = np.isin(samples.trace, val)
    return samples.subset(np.flatnonzero(~is_val)), samples.subset(np.flatnonzero(is_val))


def forbidden_trace(path: Path) -> str | None:
    """The held-out test trace ``path`` is (or lies in), or None; matched on whole path components, so that
    another phone of a test drive (``Pixel4XL`` beside ``Pixel4``) stays usable."""
    s = Path(path).resolve().as_posix() + "/"
    return next((bad for bad in FORBIDDEN_TRACES if f"/{bad}/" in s), None)


def check_not_forbidden(path: Path) -> None:
    """DataError when ``path`` is (or lies in) a held-out test trace (:func:`forbidden_trace`)."""
    bad = forbidden_trace(path)
    if bad is not None:
        raise DataError(f"{path}: {bad} is a held-out test trace and must not be used for training")


def load_real_traces(paths: list[str | Path], signals=("GPS_L1",), raw_sources: RawSources | None = None
                     ) -> list[Trace]:
    """Every ``<collection>/<phone>`` folder at or under ``paths`` (via :mod:`fusion.prepare.load`); folders
    with a RINEX file or GnssLogger log take their navigation from ``raw_sources`` (None: the folder's)."""
    traces = []
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise DataError(f"{p}: training data path does not exist")
        check_not_forbidden(p)                 # named explicitly: refused
        folders = find_traces(p) or [p]
        held = [f for f in folders if forbidden_trace(f)]
        if held:                               # found under a root (a Kaggle train/ folder holds them): left out
            warnings.warn(f"{p}: left out {len(held)} held-out test trace(s) found under it: "
                          + ", ".join(str(Path(f).relative_to(p)) for f in held))
        for f in folders:
            if f not in held:
                traces.append(load_trace(f, signals=tuple(signals), raw_sources=raw_sources))
        if folders == held:
            raise DataError(f"{p}: every trace under it is a held-out test trace; nothing to train on")
    return traces


def simulated_traces(n_traces: int, epochs_per_trace: int, *, seed: int, bias: bool = False,
                     toy: bool = False) -> list[Trace]:
    """Simulated training traces: :func:`fusion.sim.simulate.simulate_dataset`, or the toy generator."""
    if toy:
        return toy_dataset(n_traces, epochs_per_trace, seed=seed, bias=bias)
    # Paper's scenarios: Gaussian sigma 6 m; "bias" adds Poisson(1) satellites with +U(50, 200) m.
    out = simulate_dataset(n_traces, epochs_per_trace, seed=seed, config=SimConfig(nlos=bias))
    return out if isinstance(out, list) else [out]


def build_samples(traces: list[Trace], elev_mask_deg: float = 10.0, real: list[bool] | None = None,
                  with_wls: bool = True, with_graph: bool = False, slow_window_s: float = 0.0) -> Samples:
    """Samples of every trace; ``real[i]`` tags trace i as phone data (default: none); ``with_graph``
    also solves each trace's no-prior factor graph (``Samples.graph``); ``slow_window_s`` > 0 keeps the
    pseudoranges' fast error part (``Samples.pr_fast``)."""
    real = [False] * len(traces) if real is None else list(real)
    # index 0 per part: concat_samples numbers the traces
    return concat_samples([samples_from_trace(t, elev_mask_deg, 0, real=r, with_wls=with_wls,
                                              with_graph=with_graph, slow_window_s=slow_window_s)
                           for t, r in zip(traces, real, strict=True)])


def simulated_samples_with_clock(n_traces: int, epochs_per_trace: int, *, seed: int, bias: bool = False,
                                 elev_mask_deg: float = 10.0) -> Samples:
    """Simulated samples that also carry the simulator's TRUE receiver clock (``Samples.clock``).

    EXPERIMENT ONLY: for reproducing the paper's leaky protocol (``FeatureConfig(clock="given")``). Same
    traces as :func:`simulated_traces` with the same arguments.
    """
    res = simulate_dataset(n_traces, epochs_per_trace, seed=seed, config=SimConfig(nlos=bias), results=True)
    return concat_samples([samples_from_trace(r.trace, elev_mask_deg, 0, clock=r.clock_m) for r in res])
