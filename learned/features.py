"""Network inputs and targets at an initial position guess (paper Sec. "Position correction").

Per satellite slot the network sees ``[residual / res_scale, los_n, los_e, los_d]`` (the paper's four
inputs; ``los_d = -sin(elevation)``, so elevation is among them) and, when ``FeatureConfig.inputs`` asks for
them, context channels that do not depend on the guess (:func:`context_channels`, from
:mod:`learned.context`): the phone's reported pseudorange uncertainty, C/N0, the residual change since the
previous epoch and the age of the satellite's tracking arc.

- geometry is Sagnac-rotated exactly as :func:`fusion.geometry.line_of_sight` (the same model WLS uses);
- ``raw = pr - range(guess)`` still contains the receiver clock (often 1e5 m and more on phones), which is
  *estimated*, never taken from truth: ``clock_hat = median over the epoch's real slots of raw``.
  The median (not the mean) so that one multipath/NLOS-biased satellite (50-200 m) does not shift every
  other residual: the network then sees the outlier as the one large residual and the others as
  ``-los . dx`` plus noise. What removing a common offset costs: the component of ``dx`` that looks like a
  clock (roughly "up", the mean LOS direction) is only observable through the *spread* of residuals against
  the LOS vectors, exactly as in WLS, where clock and vertical are correlated;
- LOS unit vectors are expressed in the NED frame of the guess (geographic invariance, paper Sec. 4.3.1).

Target = ``(truth - guess)`` rotated into the NED frame of the guess, divided by ``out_scale``.

Two implementations: :func:`features_numpy` (reference, built on :mod:`fusion.geometry`) and
:func:`features_torch` (batched on the training device; training regenerates features every epoch).
They agree to float64 round-off (tested). Arithmetic is float64 throughout because raw pseudoranges
are ~2e7 m; only the final network inputs are cast to float32.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from fusion.geometry import C_LIGHT, OMEGA_E, ecef2ned_vec, elevation_azimuth, line_of_sight

#: Bump when the meaning or scaling of the inputs changes; checkpoints record it.
FEATURE_VERSION = 3
#: Versions this code reads: 2 (the previous release's weights: GPS L1, one clock) and 3.
SUPPORTED_VERSIONS = (2, 3)

#: Constellation of each :data:`fusion.trace.SIGNALS` index (GPS, GLO, GAL, BDS, QZS) for the "system" one-hot.
SIGNAL_SYSTEM = (0, 0, 1, 2, 2, 3, 4, 4)
N_SYSTEMS, N_SIGNALS = 5, len(SIGNAL_SYSTEM)

#: Input channel groups and their widths (version 3). "res" and "los" are the paper's and always first.
#: Each group a file may lack carries its own "present" flag (missing: flag 0 and value 0): pr_sigma (the
#: receiver's report; RINEX has none), cn0, cmd (code minus Doppler), carrier (has phase, valid, slip).
#: system / signal: one-hot with a last "unknown" entry (a signal never seen in training reads as unknown).
#: heading: present, sine and cosine of the azimuth relative to the direction of travel (absent while standing
#: still or in a lone epoch); opt-in, not among the shipped recipe's inputs (:data:`RECIPE_INPUTS`).
CHANNELS = {"res": 1, "los": 3, "pr_sigma": 2, "cn0": 2, "dres": 2, "arc": 1, "cmd": 2, "carrier": 3,
            "system": N_SYSTEMS + 1, "signal": N_SIGNALS + 1, "heading": 3}
#: The shipped recipe's inputs: every group but the opt-in "heading" (tried: worse on the GSDC drives and the
#: Pixel5, experiments/results/feature_ablation.md).
RECIPE_INPUTS = tuple(c for c in CHANNELS if c != "heading")
#: Version 2's groups and widths (its pr_sigma has no flag: every 2021 file reports one).
CHANNELS_V2 = {"res": 1, "los": 3, "pr_sigma": 1, "cn0": 2, "dres": 2, "arc": 1}
#: Groups a file may lack, each with a present flag (:data:`FLAG_CHANNEL`, see :func:`context_channels`).
OPTIONAL_GROUPS = ("pr_sigma", "cn0", "cmd", "carrier", "heading")
#: Each optional group's "present" channel within the group, and the groups bounded by construction (the
#: guard checks no range on them).
FLAG_CHANNEL = {"pr_sigma": 1, "cn0": 1, "cmd": 1, "carrier": 0, "heading": 0}
BOUNDED_GROUPS = ("carrier", "heading")
#: One-hot groups whose last channel is "unknown".
CATEGORY_GROUPS = ("system", "signal")
#: The paper's inputs.
PAPER_INPUTS = ("res", "los")
#: Reference values of the context scalings: a typical phone pseudorange sigma [m], C/N0 [dB-Hz].
_PR_SIGMA_REF_M, _CN0_REF, _CN0_SCALE = 3.0, 35.0, 10.0

# WGS-84 ellipsoid (torch geodetic latitude for the NED rotation).
_WGS84_A = 6378137.0
_WGS84_E2 = 6.69437999014e-3

#: Receiver-clock handling in the features (see FeatureConfig.clock).
CLOCK_MODES = ("median", "given")


def _check_clock(cfg: "FeatureConfig", clock) -> None:
    """A given clock only with ``clock="given"`` configs, and always with them (no silent fallback)."""
    if cfg.clock == "given" and clock is None:
        raise ValueError("FeatureConfig(clock='given') needs a per-sample clock array (experiment only)")
    if cfg.clock == "median" and clock is not None:
        raise ValueError("a clock array was passed but FeatureConfig.clock is 'median' (estimated)")


@dataclass(frozen=True)
class FeatureConfig:
    """Normalisation shared by training and inference; stored in every checkpoint.

    res_scale: residuals are divided by this [m] (a typical phone residual spread is ~10 m).
    out_scale: targets / network outputs are in units of this [m].
    elev_mask_deg: slots below this elevation (at the truth when training, at the guess at
        inference, as WLS does) are masked out.
    clock: how the receiver clock is removed from the raw residuals. ``"median"`` (the product): estimated
        from the measurements. ``"given"``: EXPERIMENT ONLY, a per-sample clock array supplied by the caller
        (the simulator's true clock), reproducing the paper's released code, which fed the true clock to
        the network at evaluation (a ground-truth leak). :class:`learned.infer.Corrector` refuses
        checkpoints with ``"given"``, so such a model can never run in the product.
    inputs: channel groups fed to the network, from :data:`CHANNELS`, starting with the paper's
        ("res", "los").
    """

    version: int = FEATURE_VERSION
    res_scale: float = 10.0
    out_scale: float = 10.0
    elev_mask_deg: float = 10.0
    clock: str = "median"
    inputs: tuple[str, ...] = PAPER_INPUTS

    def __post_init__(self):
        if self.clock not in CLOCK_MODES:
            raise ValueError(f"FeatureConfig.clock must be one of {CLOCK_MODES}, got {self.clock!r}")
        object.__setattr__(self, "inputs", tuple(self.inputs))
        if self.version not in SUPPORTED_VERSIONS:
            raise ValueError(f"FeatureConfig.version {self.version!r}: this code reads {SUPPORTED_VERSIONS}")
        unknown = [c for c in self.inputs if c not in self.widths]
        if unknown or self.inputs[:2] != PAPER_INPUTS:
            raise ValueError(f"FeatureConfig.inputs must start with {PAPER_INPUTS} and name channels from "
                             f"{tuple(self.widths)}; got {self.inputs}")

    @property
    def widths(self) -> dict[str, int]:
        """Channel groups of this version and their widths."""
        return CHANNELS_V2 if self.version == 2 else CHANNELS

    @property
    def n_inputs(self) -> int:
        """Input width per slot."""
        return sum(self.widths[c] for c in self.inputs)

    def slices(self) -> dict[str, slice]:
        """Each input group's channels in ``x`` (N,S,n_inputs)."""
        out, a = {}, 0
        for c in self.inputs:
            out[c] = slice(a, a + self.widths[c])
            a += self.widths[c]
        return out

    def to_dict(self) -> dict:
        d = asdict(self)
        d["inputs"] = list(self.inputs)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "FeatureConfig":
        keys = ("version", "res_scale", "out_scale", "elev_mask_deg", "clock", "inputs")
        return cls(**{k: d[k] for k in keys if k in d})


def context_channels(ctx: dict[str, np.ndarray], mask: np.ndarray, cfg: FeatureConfig,
                     missing: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """The context channels ``cfg.inputs`` asks for beyond the paper's: (N,S,C) float32, zeros on padding.

    ctx: (N,S) arrays keyed as :data:`learned.context.CONTEXT_KEYS`; mask (N,S) bool real slots.
    missing: group name -> (N,S) bool slots where that group is to read as missing (optional groups) or
    unknown (system / signal): training's feature dropout and the guard (:mod:`learned.guard`).
    """
    if cfg.version == 2:
        return _context_channels_v2(ctx, mask, cfg)
    missing = missing or {}
    drop = {k: np.asarray(missing.get(k, False), bool) for k in (*OPTIONAL_GROUPS, *CATEGORY_GROUPS)}
    cols = []
    for name in cfg.inputs[2:]:
        cols += _group(name, ctx, drop, cfg)
    if not cols:
        return np.zeros(mask.shape + (0,), np.float32)
    x = np.stack([np.broadcast_to(np.asarray(c, float), mask.shape) for c in cols], axis=-1)
    return np.where(mask[..., None], x, 0.0).astype(np.float32)


def _group(name: str, ctx: dict, drop: dict, cfg: FeatureConfig) -> list:
    """The (N,S) columns of one version-3 input group."""
    if name == "pr_sigma":
        have = (np.asarray(ctx["pr_sigma_ok"]) > 0) & ~drop["pr_sigma"]
        return [np.where(have, np.log(np.clip(ctx["pr_sigma"], 0.1, 1000.0) / _PR_SIGMA_REF_M), 0.0), have]
    if name == "cn0":
        have = (ctx["cn0"] > 0) & ~drop["cn0"]
        return [np.where(have, (ctx["cn0"] - _CN0_REF) / _CN0_SCALE, 0.0), have]
    if name == "dres":
        return [np.clip(ctx["dres"] / cfg.res_scale, -10.0, 10.0), ctx["prev_ok"]]
    if name == "arc":
        return [np.log1p(ctx["arc_s"]) / np.log1p(600.0)]
    if name == "cmd":
        have = (np.asarray(ctx["cmd_ok"]) > 0) & ~drop["cmd"]
        return [np.where(have, np.clip(ctx["cmd"] / cfg.res_scale, -10.0, 10.0), 0.0), have]
    if name == "carrier":
        has = (np.asarray(ctx["adr_has"]) > 0) & ~drop["carrier"]
        return [has, has & (np.asarray(ctx["adr_ok"]) > 0), has & (np.asarray(ctx["adr_slip"]) > 0)]
    if name == "heading":
        has = (np.asarray(ctx["heading_ok"]) > 0) & ~drop["heading"]
        return [has, np.where(has, ctx["rel_sin"], 0.0), np.where(has, ctx["rel_cos"], 0.0)]
    sig = np.asarray(ctx["signal"], np.int64)
    known = (sig >= 0) & (sig < N_SIGNALS)
    if name == "system":
        idx = np.where(known & ~drop["system"], np.asarray(SIGNAL_SYSTEM)[np.clip(sig, 0, N_SIGNALS - 1)], N_SYSTEMS)
        return list(np.eye(N_SYSTEMS + 1, dtype=bool)[idx].transpose(2, 0, 1))
    idx = np.where(known & ~drop["signal"], sig, N_SIGNALS)
    return list(np.eye(N_SIGNALS + 1, dtype=bool)[idx].transpose(2, 0, 1))


def _context_channels_v2(ctx: dict[str, np.ndarray], mask: np.ndarray, cfg: FeatureConfig) -> np.ndarray:
    """Version 2's context channels (the previous release's weights), unchanged."""
    cols = []
    for name in cfg.inputs[2:]:
        if name == "pr_sigma":
            cols.append(np.log(np.clip(ctx["pr_sigma"], 0.1, 1000.0) / _PR_SIGMA_REF_M))
        elif name == "cn0":
            have = ctx["cn0"] > 0
            cols += [np.where(have, (ctx["cn0"] - _CN0_REF) / _CN0_SCALE, 0.0), have]
        elif name == "dres":
            cols += [np.clip(ctx["dres"] / cfg.res_scale, -10.0, 10.0), ctx["prev_ok"]]
        elif name == "arc":
            cols.append(np.log1p(ctx["arc_s"]) / np.log1p(600.0))
    if not cols:
        return np.zeros(mask.shape + (0,), np.float32)
    return np.where(mask[..., None], np.stack([np.asarray(c, float) for c in cols], axis=-1), 0.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------- numpy
def masked_median_numpy(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Lower median over axis 1 of (B, S) ``values`` where ``mask``; 0 for rows with no real slot.

    "Lower" (the smaller middle value for even counts) to match :meth:`torch.Tensor.nanmedian`.
    """
    v = np.where(mask, values, np.inf)
    v = np.sort(v, axis=1)
    n = mask.sum(axis=1)
    k = np.maximum((n - 1) // 2, 0)
    med = np.take_along_axis(v, k[:, None], axis=1)[:, 0]
    return np.where(n > 0, med, 0.0)


def features_numpy(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray, guess: np.ndarray,
                   cfg: FeatureConfig = FeatureConfig(), clock: np.ndarray | None = None,
                   extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Reference features. sat_pos (B,S,3), pr (B,S), mask (B,S) bool, guess (B,3) ECEF;
    ``clock`` (B,) [m] only with ``cfg.clock == "given"`` (experiment only); ``extra`` (B,S,C) the
    :func:`context_channels` appended after the paper's four.

    Returns ``x`` (B,S,4+C) float32 (zeros in padded slots) and the clock used (B,) [m].
    """
    _check_clock(cfg, clock)
    rng, los = line_of_sight(sat_pos, guess)
    raw = pr - rng
    clock = masked_median_numpy(raw, mask) if clock is None else np.asarray(clock, float)
    res = np.where(mask, (raw - clock[:, None]) / cfg.res_scale, 0.0)
    los_ned = np.where(mask[..., None], ecef2ned_vec(los, guess[:, None, :]), 0.0)   # NaN padding stays out
    parts = [res[..., None], los_ned] + ([] if extra is None else [extra])
    return np.concatenate(parts, axis=-1).astype(np.float32), clock


def target_numpy(truth: np.ndarray, guess: np.ndarray, cfg: FeatureConfig = FeatureConfig()) -> np.ndarray:
    """(truth - guess) in the NED frame of the guess, over ``out_scale``: (B,3)."""
    return ecef2ned_vec(truth - guess, guess) / cfg.out_scale


# ---------------------------------------------------------------------------------------------- torch
def ned_rotation_torch(ref: torch.Tensor) -> torch.Tensor:
    """(B,3) ECEF -> (B,3,3) rotation ECEF->NED at geodetic latitude/longitude of ``ref``.

    Geodetic latitude by fixed-point iteration (5 steps reach < 1e-12 rad near the surface).
    """
    import torch  # training only: inference never imports torch
    x, y, z = ref.unbind(-1)
    p = torch.sqrt(x * x + y * y)
    lon = torch.atan2(y, x)
    lat = torch.atan2(z, p * (1.0 - _WGS84_E2))
    for _ in range(5):
        s = torch.sin(lat)
        n = _WGS84_A / torch.sqrt(1.0 - _WGS84_E2 * s * s)
        h = p / torch.cos(lat) - n
        lat = torch.atan2(z, p * (1.0 - _WGS84_E2 * n / (n + h)))
    sl, cl, so, co = torch.sin(lat), torch.cos(lat), torch.sin(lon), torch.cos(lon)
    zero = torch.zeros_like(sl)
    return torch.stack([
        torch.stack([-sl * co, -sl * so, cl], -1),
        torch.stack([-so, co, zero], -1),
        torch.stack([-cl * co, -cl * so, -sl], -1),
    ], -2)


def line_of_sight_torch(sat_pos: torch.Tensor, rx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Torch twin of :func:`fusion.geometry.line_of_sight`: (B,S,3), (B,3) -> range (B,S), los (B,S,3)."""
    import torch  # training only: inference never imports torch
    rng0 = torch.linalg.vector_norm(sat_pos - rx[:, None, :], dim=-1)
    theta = OMEGA_E * rng0 / C_LIGHT
    c, s = torch.cos(theta), torch.sin(theta)
    sx, sy, sz = sat_pos.unbind(-1)
    rot = torch.stack([c * sx + s * sy, -s * sx + c * sy, sz], -1)
    d = rot - rx[:, None, :]
    rng = torch.linalg.vector_norm(d, dim=-1)
    return rng, d / rng.clamp_min(1.0)[..., None]


def features_torch(sat_pos: torch.Tensor, pr: torch.Tensor, mask: torch.Tensor, guess: torch.Tensor,
                   cfg: FeatureConfig = FeatureConfig(), clock: torch.Tensor | None = None,
                   extra: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Batched features on any device. Inputs float64: sat_pos (B,S,3), pr (B,S), mask (B,S) bool,
    guess (B,3); ``clock`` (B,) [m] only with ``cfg.clock == "given"`` (experiment only); ``extra``
    (B,S,C) float32 context channels (:func:`context_channels`).
    Returns ``x`` (B,S,4+C) float32 and the NED rotation at the guess (B,3,3) float64."""
    import torch  # training only: inference never imports torch
    _check_clock(cfg, clock)
    rng, los = line_of_sight_torch(sat_pos, guess)
    raw = pr - rng
    if clock is None:
        # nanmedian returns the lower middle value for even counts (same as masked_median_numpy).
        clock = torch.nan_to_num(raw.masked_fill(~mask, float("nan")).nanmedian(dim=1).values, nan=0.0)
    res = ((raw - clock[:, None]) / cfg.res_scale).masked_fill(~mask, 0.0)
    R = ned_rotation_torch(guess)
    los_ned = torch.einsum("bij,bsj->bsi", R, los).masked_fill(~mask[..., None], 0.0)   # NaN padding stays out
    x = torch.cat([res[..., None], los_ned], -1).float()
    return (x if extra is None else torch.cat([x, extra.float()], -1)), R


def target_torch(truth: torch.Tensor, guess: torch.Tensor, R: torch.Tensor,
                 cfg: FeatureConfig = FeatureConfig()) -> torch.Tensor:
    """(truth - guess) in the NED frame of the guess (R from :func:`features_torch`) over out_scale."""
    import torch  # training only: inference never imports torch
    return torch.einsum("bij,bj->bi", R, truth - guess).float() / cfg.out_scale


def compact_slots(sat_pos: np.ndarray, pr: np.ndarray, mask: np.ndarray, *extra: np.ndarray) -> tuple:
    """Move each epoch's real slots to the front and drop the all-padding tail.

    sat_pos (N,S,3), pr (N,S), mask (N,S) bool, and any ``extra`` (N,S[,k]) arrays slotted the same way;
    returns them in that order with S' = the most real slots of any epoch (>= 1) slots. Padded slots keep
    whatever the inputs held there. The network's output does not depend on slot order or padding, but its
    cost grows with S: traces are padded to the most slots of any epoch *before* the elevation mask
    (measured on the shipped trace: S 10 -> 8, about 20 % less network time).
    """
    order = np.argsort(~mask, axis=1, kind="stable")[:, :max(int(mask.sum(1).max(initial=0)), 1)]

    def take(a: np.ndarray) -> np.ndarray:
        return np.take_along_axis(a, order.reshape(order.shape + (1,) * (a.ndim - 2)), axis=1)
    return tuple(take(a) for a in (sat_pos, pr, mask, *extra))


def elevation_mask(sat_pos: np.ndarray, mask: np.ndarray, at: np.ndarray, min_deg: float) -> np.ndarray:
    """``mask`` & (elevation seen from ``at`` (B,3) >= min_deg): (B,S) bool. Same test WLS applies."""
    _, los = line_of_sight(sat_pos, at)
    el, _ = elevation_azimuth(los, at)
    return mask & (el >= min_deg)
