"""Geometry-based data augmentation (paper Alg. 1), batched on the training device.

A new initial guess per sample: ``guess = truth + R_ned(truth)^T u`` with ``u ~ U(-eta, eta)^3``, i.e. the
box is axis-aligned in the **NED frame of the truth** (north, east, down half-widths all ``eta``). The paper
states the box in ECEF; NED makes the box mean the same thing everywhere on the globe, which is what the
NED-frame network is meant to be invariant to. Features and targets are then regenerated at the guess.

The box alone teaches roughly a least-squares step, which is ~0 from the WLS solution the network starts
from at inference. :func:`draw_mixed_guesses` therefore mixes the box with each sample's own WLS position
(computed from its measurements only, :mod:`learned.data`) plus a small jitter: the inference distribution.
A third source, ``graph``, is each sample's own solution of the factor graph *without* the learned prior
(``fused-nodnn``, also measurement-only): where the fused mode asks the network (``prior_at="graph"``).
"""
from __future__ import annotations

import math

import torch

from learned.features import ned_rotation_torch


def draw_guesses(truth: torch.Tensor, eta: float, generator: torch.Generator) -> torch.Tensor:
    """(B,3) float64 ECEF truths -> (B,3) guesses, uniform in the NED box of half-width ``eta`` [m].

    ``generator`` must live on ``truth.device``; the draw is reproducible for a given generator state.
    """
    u = (torch.rand(truth.shape, generator=generator, device=truth.device, dtype=torch.float64) * 2.0 - 1.0) * eta
    R = ned_rotation_torch(truth)
    return truth + torch.einsum("bji,bj->bi", R, u)


def epoch_generator(seed: int, epoch: int, device: torch.device | str = "cpu", rank: int = 0) -> torch.Generator:
    """Generator for one training epoch, derived from (seed, epoch, rank) so that resuming reproduces the
    draws of an uninterrupted run without saving RNG states, and each distributed rank draws its own
    augmentation stream (rank 0 draws what a one-process run draws)."""
    g = torch.Generator(device=device)
    g.manual_seed((int(seed) * 1_000_003 + int(epoch) * 7_919 + 12_345 + int(rank) * 104_729) % (2**63))
    return g


# ------------------------------------------------------------------------------------ realistic guesses
#: Guess sources a mix may name: the paper's box around the truth, the WLS solution (+ jitter), and the
#: no-prior factor-graph solution (+ the same jitter).
GUESS_SOURCES = ("box", "wls", "graph")
#: Sources always present in a parsed mix; the others appear only when their fraction is > 0, so mixes
#: written before ``graph`` existed parse (and are stored in checkpoints) exactly as before.
_ALWAYS = ("box", "wls")


def parse_guess_mix(text: str | dict) -> dict[str, float]:
    """``"box=0.5,wls=0.5"`` (or a dict) -> normalised fractions ``{"box": .5, "wls": .5}``.

    ``box`` and ``wls`` are always in the result; ``graph`` only when its fraction is > 0.

    Raises ValueError naming the bad part (unknown source, not a number, negative, all zero).
    """
    if isinstance(text, dict):
        items = list(text.items())
    else:
        items = []
        for part in (p.strip() for p in str(text).split(",") if p.strip()):
            if "=" not in part:
                raise ValueError(f"guess mix {text!r}: {part!r} is not SOURCE=FRACTION")
            k, v = part.split("=", 1)
            try:
                items.append((k.strip(), float(v)))
            except ValueError:
                raise ValueError(f"guess mix {text!r}: {v!r} is not a number") from None
    mix = {k: 0.0 for k in GUESS_SOURCES}
    for k, v in items:
        if k not in GUESS_SOURCES:
            raise ValueError(f"guess mix {text!r}: unknown source {k!r} (choose from {', '.join(GUESS_SOURCES)})")
        if not (v >= 0 and math.isfinite(v)):
            raise ValueError(f"guess mix {text!r}: fraction of {k!r} must be a finite number >= 0")
        mix[k] += float(v)
    total = sum(mix.values())
    if total <= 0:
        raise ValueError(f"guess mix {text!r}: fractions sum to zero")
    return {k: v / total for k, v in mix.items() if k in _ALWAYS or v > 0}


def draw_mixed_guesses(truth: torch.Tensor, wls: torch.Tensor, usable: torch.Tensor, eta: float,
                       box_frac: float, jitter: float, generator: torch.Generator,
                       graph: torch.Tensor | None = None, graph_usable: torch.Tensor | None = None,
                       graph_frac: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Per sample: with probability ``box_frac`` the paper's box guess (:func:`draw_guesses`), otherwise
    the sample's own WLS position plus NED jitter U(-jitter, jitter) per axis.

    truth, wls: (B,3) float64 ECEF; usable: (B,) bool, False where the sample has no (usable) WLS
    position: those fall back to the box. Returns guesses (B,3) and ``is_box`` (B,) bool.
    The WLS positions come from the measurements alone, so the WLS branch is exactly the inference-time
    guess (up to the jitter, an augmentation); only the box branch is built from the truth.

    graph, graph_usable: (B,3) no-prior graph positions and (B,) bool; with ``graph_frac`` > 0 a sample
    whose draw falls in [box_frac, box_frac + graph_frac) takes its graph position + the same jitter
    (falling back to WLS, then the box, where unusable). The draws are the same random numbers as
    without a graph, so ``graph_frac=0`` reproduces the two-source mix bit for bit.
    """
    box = draw_guesses(truth, eta, generator)
    pick = torch.rand(truth.shape[0], generator=generator, device=truth.device, dtype=torch.float64)
    u = (torch.rand(truth.shape, generator=generator, device=truth.device, dtype=torch.float64) * 2.0 - 1.0) * jitter
    if graph is not None and graph_frac > 0:
        take = (pick >= box_frac) & (pick < box_frac + graph_frac) & graph_usable
        wls = torch.where(take[:, None], graph, wls)
        usable = usable | take
    w = torch.where(usable[:, None], wls, truth)          # truth only as a placeholder, replaced below
    near_wls = w + torch.einsum("bji,bj->bi", ned_rotation_torch(w), u)
    is_box = (pick < box_frac) | ~usable
    return torch.where(is_box[:, None], box, near_wls), is_box


# ------------------------------------------------------------------------------------ satellite thinning
#: Slots whose satellite positions lie closer than this [m] are one satellite's signals (L1 and L5 of one
#: satellite differ by their transmit times' microseconds: millimetres; two satellites by thousands of km).
SAME_SATELLITE_M = 1000.0
#: Fewest satellites a thinned sample keeps: a position and a clock.
THIN_MIN_SATS = 4


def satellite_groups(sat_pos: torch.Tensor, mask: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """(N,S) long: for each slot the index of the first real slot of the same satellite (its own index
    where it is the first, or not real). sat_pos (N,S,3) ECEF [m], mask (N,S) bool."""
    S = mask.shape[1]
    out = []
    for a in range(0, mask.shape[0], chunk):
        p, m = sat_pos[a:a + chunk], mask[a:a + chunk]
        same = (torch.cdist(p, p) < SAME_SATELLITE_M) & m[:, None, :] & m[:, :, None]       # (n,S,S)
        first = torch.where(same, torch.arange(S, device=p.device), S).min(dim=2).values
        out.append(torch.where(m, first, torch.arange(S, device=p.device)))
    return torch.cat(out)


def thin_satellites(mask: torch.Tensor, groups: torch.Tensor, rate: float,
                    generator: torch.Generator) -> torch.Tensor:
    """Satellite dropout: with probability ``rate`` a sample keeps only k of its n satellites (all their
    signals), k uniform in [THIN_MIN_SATS, n], the rest read as blocked, as a street canyon blocks them.
    Teaches the network the few-satellite sets that open-sky training drives rarely hold.

    mask (N,S) bool, groups (N,S) from :func:`satellite_groups`; returns the thinned mask (N,S). The draws from
    ``generator`` are the same whatever the rate."""
    N, S = mask.shape
    dev = mask.device
    u = torch.rand((N, S), generator=generator, device=dev, dtype=torch.float64)
    pick = torch.rand(N, generator=generator, device=dev, dtype=torch.float64)
    frac = torch.rand(N, generator=generator, device=dev, dtype=torch.float64)
    first = mask & (groups == torch.arange(S, device=dev))                     # one slot per satellite
    n = first.sum(1)
    key = torch.where(first, u, torch.inf)
    order = torch.arange(S, device=dev, dtype=key.dtype).expand(N, S)
    rank = torch.empty_like(key).scatter_(1, key.argsort(1), order)             # each satellite's place in the draw
    span = (n - THIN_MIN_SATS + 1).clamp_min(1)
    k = THIN_MIN_SATS + torch.floor(frac * span).to(n.dtype)
    keep_sat = rank < k[:, None]                                               # on first slots
    keep = torch.gather(keep_sat, 1, groups)
    thinned = (pick < rate) & (n > THIN_MIN_SATS)
    return mask & (keep | ~thinned[:, None])
