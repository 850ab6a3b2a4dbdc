"""The learned Doppler head: each pseudorange rate's sigma as a learned multiplier on the graph's physical
model, and its probability of being an outlier (a reflected path's Doppler), from what the log itself says.

A phone's Doppler sigma is a tracking-loop figure that knows nothing of the reflected paths of a street
canyon, whose Doppler differs from the direct path's by metres per second. The head reads, per Doppler
measurement, without truth: the C/N0 (or that there is none), the elevation, the constellation and whether
it is a second frequency, its residual in the epoch's robust one-epoch fit of velocity and drift
(:func:`fusion.estimate.graph.consistency.epoch_fit`) in units of that epoch's robust scale, that scale against
the trace's typical one, how many Doppler measurements the epoch has and the speed of the initial track. A
small per-measurement network (:data:`FEATURES` -> hidden -> hidden -> 2, ReLU) gives ``m`` (the log
multiplier, bounded to +-``M_BOUND``) and ``p`` (the outlier probability); the factor
``exp(m) * sqrt(1 - p + p K^2)`` is the standard deviation of the two-component mixture the head was trained
with (:mod:`learned.doppler_train`: inliers ``N(0, (sigma_phys e^m)^2)``, outliers ``K`` times wider). The
graph's sigma is ``sigma_phys`` times that factor divided by its epoch's median factor (:func:`relative`): the
head weighs an epoch's Doppler against each other, and the absolute level stays the physical model's, which
the consistency check raises where the log shows it too small.

Its guard acts per measurement: a constellation it never saw, or a feature outside the range it was trained
on, keeps the physical model (both counted). The head lives in the checkpoint's config (``doppler_head``:
plain lists, so the ``.npz`` twin carries it and inference needs no torch).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from fusion.errors import CheckpointError
from fusion.estimate.graph.consistency import MAD_TO_SIGMA, doppler_fit, row_medians
from fusion.geometry import elevation_azimuth, line_of_sight, ned_rotation
from fusion.trace import SIGNALS, Trace

if TYPE_CHECKING:
    from fusion.estimate.graph.inputs import EpochInputs

FORMAT_VERSION = 1
SYSTEMS = ("GPS", "GLO", "GAL", "BDS", "QZS")
FIRST_FREQUENCY = ("GPS_L1", "GLO_G1", "GAL_E1", "BDS_B1I", "QZS_J1", "BDS_B1C")
#: per-measurement inputs, in order (``*_present`` flags say whether the value exists: 0 inputs then)
FEATURES = ("cn0_present", "cn0", "sin_el", "z_present", "z", "abs_z", "epoch_scale", "n_doppler", "speed",
            "second_freq") + tuple(f"sys_{s}" for s in SYSTEMS)
#: the continuous inputs the guard holds to their training range (the flags and one-hots need no range)
GUARDED = ("cn0", "sin_el", "epoch_scale", "n_doppler", "speed")
#: the guard's range is the training range widened by this share of its span on each side
RANGE_MARGIN = 0.1
#: the outliers' sigma in units of the inliers'
OUTLIER_RATIO = 10.0
#: the log multiplier is bounded to +-M_BOUND (a factor of ~12 either way)
M_BOUND = 2.5
#: residuals are clipped here [standardised units]
Z_CLIP = 10.0


def _system_index(signal: np.ndarray) -> np.ndarray:
    """(N,) index into SYSTEMS of each signal index (N,), -1 for none."""
    table = np.array([SYSTEMS.index(s[:3]) if s[:3] in SYSTEMS else -1 for s in SIGNALS])
    return table[signal]


def fit_inputs(trace: Trace, inp: "EpochInputs", ks: np.ndarray, ss: np.ndarray) -> dict:
    """The inputs from each epoch's robust one-epoch fit of velocity and drift
    (:func:`fusion.estimate.graph.consistency.doppler_fit`), for the measurements at (ks, ss): the residual
    in units of its epoch's robust scale (``z``, ``abs_z``, with ``z_present``: epochs with too few
    measurements have none) and that scale against the trace's typical one (``epoch_scale``). Scale-free,
    so that a phone whose stated sigmas are k times too cautious reads as one whose sigmas are right. Each
    value (N,)."""
    z = doppler_fit(trace, inp)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = MAD_TO_SIGMA * row_medians(np.abs(z))
        zk = z[ks, ss] / scale[ks]
    typical = np.nanmedian(scale) if np.isfinite(scale).any() else 1.0
    zc = np.clip(np.nan_to_num(zk, posinf=Z_CLIP, neginf=-Z_CLIP), -Z_CLIP, Z_CLIP)
    return {"z_present": np.isfinite(zk), "z": zc / 3.0, "abs_z": np.log1p(np.abs(zc)),
            "epoch_scale": np.log(np.nan_to_num(scale[ks] / typical, nan=1.0).clip(0.01, 100.0))}


def signal_inputs(trace: Trace, ks: np.ndarray, ss: np.ndarray) -> dict:
    """The inputs of each measurement's signal at (ks, ss): C/N0 (``cn0``, with ``cn0_present``), second
    frequency and the constellation one-hot. Each value (N,)."""
    cn0 = np.zeros(len(ks)) if trace.cn0 is None else np.asarray(trace.cn0, float)[ks, ss]
    sig = trace.signal[ks, ss]
    sys_idx = _system_index(sig)
    return {"cn0_present": cn0 > 0, "cn0": np.where(cn0 > 0, (cn0 - 35.0) / 10.0, 0.0),
            "second_freq": ~np.isin(sig, [SIGNALS.index(s) for s in FIRST_FREQUENCY]),
            **{f"sys_{s}": sys_idx == i for i, s in enumerate(SYSTEMS)}}


def doppler_features(trace: Trace, inp: "EpochInputs") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x (N, len(FEATURES)) float32 for the N Doppler measurements the graph uses (``inp.raw.doppler`` at
    kept epochs, their sigmas ``inp.raw.prr_sigma`` the physical model's), and their epoch and slot
    indices ks, ss (N,). Truth-free: everything comes from the log and the initial track."""
    use = inp.raw.doppler & inp.keep[:, None]
    ks, ss = np.nonzero(use)
    if not len(ks):
        return np.zeros((0, len(FEATURES)), np.float32), ks, ss
    # one slot per row: (N,1,3) satellites seen from (N,3) receivers, the NED frames made once per epoch
    R = ned_rotation(inp.init_pos)[ks]
    el, _ = elevation_azimuth(line_of_sight(trace.sat_pos[ks, ss][:, None], inp.init_pos[ks])[1], None, R)
    f = {**fit_inputs(trace, inp, ks, ss), **signal_inputs(trace, ks, ss),
         "sin_el": np.sin(np.radians(el[:, 0])), "n_doppler": (use.sum(axis=1)[ks] - 8.0) / 8.0,
         "speed": np.log1p(np.linalg.norm(inp.init_vel[ks], axis=1))}
    return np.stack([f[name] for name in FEATURES], axis=1).astype(np.float32), ks, ss


def _mlp(head: dict, x: np.ndarray) -> np.ndarray:
    """(N,2) raw outputs of the head's network for x (N,F) (float32, as the torch module)."""
    h = x.astype(np.float32)
    layers = head["layers"]
    for i, (w, b) in enumerate(layers):
        h = h @ np.asarray(w, np.float32).T + np.asarray(b, np.float32)
        if i < len(layers) - 1:
            h = np.maximum(h, 0.0)
    return h


def head_outputs(head: dict, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """m (N,) the bounded log multiplier and p (N,) the outlier probability for inputs x (N,F)."""
    out = _mlp(head, x).astype(float)
    return M_BOUND * np.tanh(out[:, 0] / M_BOUND), 1.0 / (1.0 + np.exp(-out[:, 1]))


def sigma_multiplier(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N,) the factor on the physical sigma: the standard deviation of the inlier / outlier mixture."""
    return np.exp(m) * np.sqrt(1.0 - p + p * OUTLIER_RATIO ** 2)


def relative(mult: np.ndarray, ks: np.ndarray, ss: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(N,) multipliers ``mult`` (N,) of the measurements at (ks, ss) divided by their epoch's median (in logs):
    the head weighs an epoch's Doppler measurements against each other, and the absolute level stays the
    physical model's, which the consistency check raises where the log shows it too small (a head trained on
    one receiver's stated sigmas cannot know another's)."""
    logs = np.full(shape, np.nan)
    logs[ks, ss] = np.log(mult)
    return mult / np.exp(np.nan_to_num(row_medians(logs)))[ks]


def check_head(head, path) -> dict:
    """``head`` (a checkpoint config's ``doppler_head``) when this code can run it; CheckpointError naming
    ``path`` otherwise."""
    try:
        ok = head.get("version") == FORMAT_VERSION and tuple(head["features"]) == FEATURES
        shapes = [np.shape(w) for w, _ in head["layers"]]
        ok = ok and shapes[0][1] == len(FEATURES) and shapes[-1][0] == 2 and len(head["range"]) == len(GUARDED)
    except (AttributeError, KeyError, TypeError, ValueError, IndexError):
        ok = False
    if not ok:
        raise CheckpointError(f"{path}: its doppler_head is not one this code reads (version {FORMAT_VERSION}, "
                              f"features {', '.join(FEATURES)})")
    return head


def guard(head: dict, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool measurements of a constellation the head never saw, and (N,) bool with a guarded input
    outside its training range: both keep the physical model."""
    sys_cols = [FEATURES.index(f"sys_{s}") for s in SYSTEMS]
    seen = np.array([s in head.get("systems", SYSTEMS) for s in SYSTEMS])
    unseen = ~(x[:, sys_cols] @ seen.astype(np.float32) > 0.5)
    lo, hi = np.asarray(head["range"], float).T
    lo, hi = lo - RANGE_MARGIN * (hi - lo), hi + RANGE_MARGIN * (hi - lo)
    hi[GUARDED.index("sin_el")] = 1.0            # the zenith is in range whether or not training saw it
    cols = x[:, [FEATURES.index(g) for g in GUARDED]]
    # a missing C/N0 reads 0 and is the cn0_present flag's business, not a range violation
    missing = np.zeros_like(cols, bool)
    missing[:, GUARDED.index("cn0")] = x[:, FEATURES.index("cn0_present")] < 0.5
    out = (((cols < lo) | (cols > hi)) & ~missing).any(axis=1)
    return unseen, out & ~unseen


class DopplerNoise:
    """The head as the graph's Doppler noise: called with the trace and the graph's inputs once its Doppler
    factors are chosen (:func:`fusion.estimate.graph.inputs.prepare_inputs`), it multiplies
    ``inp.raw.prr_sigma`` in place and returns the counts for the run's report."""

    def __init__(self, head: dict):
        self.head = head

    def __call__(self, trace: Trace, inp: "EpochInputs") -> dict:
        x, ks, ss = doppler_features(trace, inp)
        unseen, out = guard(self.head, x)
        m, p = head_outputs(self.head, x)
        learned = ~(unseen | out)
        mult = relative(np.where(learned, sigma_multiplier(m, p), 1.0), ks, ss, inp.raw.doppler.shape)
        inp.raw.prr_sigma[ks, ss] *= mult
        return {"doppler_sigmas": int(learned.sum()), "doppler_unseen_system": int(unseen.sum()),
                "doppler_out_of_range": int(out.sum()), "doppler_likely_outliers": int((p[learned] > 0.5).sum())}
