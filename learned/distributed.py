"""Data-parallel training under ``torchrun`` (or one process without it), kept to a few named calls.

``torchrun --nproc_per_node N -m fusion.cli train ...`` sets ``WORLD_SIZE``/``RANK``/``LOCAL_RANK``; the
process group is then gloo on CPU and nccl on GPU. Each rank trains on its shard of every epoch's shared
permutation and the gradients are averaged by an all-reduce after each backward pass (what
DistributedDataParallel does, written out so that the per-satellite losses, which need the raw
pseudoranges beside the network, stay in the training step unchanged). Everything here is a no-op in a
single process.
"""
from __future__ import annotations

import os

import torch
import torch.distributed as tdist


def world_size() -> int:
    return tdist.get_world_size() if tdist.is_initialized() else 1


def rank() -> int:
    return tdist.get_rank() if tdist.is_initialized() else 0


def is_main() -> bool:
    return rank() == 0


def init_from_env(device: str) -> None:
    """Join the process group when launched by torchrun (``WORLD_SIZE`` > 1)."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not tdist.is_initialized():
        tdist.init_process_group("nccl" if device == "cuda" else "gloo")


def device_for(device: str) -> torch.device:
    """The torch device of this rank: ``cuda:LOCAL_RANK`` on GPU, else CPU."""
    if device == "cuda" and torch.cuda.is_available():
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return torch.device(device)


def shard(order: torch.Tensor) -> torch.Tensor:
    """This rank's rows of a permutation (N,): every ``world_size``-th of the first ``N - N % world_size``,
    so every rank runs the same number of batches (a rank with one batch more would wait forever in the
    gradient all-reduce)."""
    n = order.numel() - order.numel() % world_size()
    return order[:n][rank()::world_size()]


def broadcast_parameters(model: torch.nn.Module) -> None:
    """Start every rank from rank 0's weights."""
    if world_size() > 1:
        for p in model.parameters():
            tdist.broadcast(p.data, 0)


def average_gradients(model: torch.nn.Module) -> None:
    """All-reduce mean of the gradients (ranks with unequal last batches weigh the same)."""
    n = world_size()
    if n == 1:
        return
    for p in model.parameters():
        if p.grad is not None:
            tdist.all_reduce(p.grad, op=tdist.ReduceOp.SUM)
            p.grad /= n


def barrier() -> None:
    if world_size() > 1:
        tdist.barrier()


def shutdown() -> None:
    if tdist.is_initialized():
        tdist.destroy_process_group()
