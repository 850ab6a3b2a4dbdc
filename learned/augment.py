"""Geometry-based data augmentation (paper Alg. 1), batched on the training device.

A new initial guess per sample: ``guess = truth + R_ned(truth)^T u`` with ``u ~ U(-eta, eta)^3``, i.e. the
box is axis-aligned in the **NED frame of the truth** (north, east, down half-widths all ``eta``). The paper
states the box in ECEF; NED makes the box mean the same thing everywhere on the globe, which is what the
NED-frame network is meant to be invariant to. Features and targets are then regenerated at the guess.
"""
from __future__ import annotations

import torch

from learned.features import ned_rotation_torch


def draw_guesses(truth: torch.Tensor, eta: float, generator: torch.Generator) -> torch.Tensor:
    """(B,3) float64 ECEF truths -> (B,3) guesses, uniform in the NED box of half-width ``eta`` [m].

    ``generator`` must live on ``truth.device``; the draw is reproducible for a given generator state.
    """
    u = (torch.rand(truth.shape, generator=generator, device=truth.device, dtype=torch.float64) * 2.0 - 1.0) * eta
    R = ned_rotation_torch(truth)
    return truth + torch.einsum("bji,bj->bi", R, u)


def epoch_generator(seed: int, epoch: int, device: torch.device | str = "cpu") -> torch.Generator:
    """Generator for one training epoch, derived from (seed, epoch) so that resuming reproduces the
    draws of an uninterrupted run without saving RNG states."""
    g = torch.Generator(device=device)
    g.manual_seed((int(seed) * 1_000_003 + int(epoch) * 7_919 + 12_345) % (2**63))
    return g
