"""Save and load model checkpoints with clear :class:`CheckpointError` messages.

A checkpoint is a plain dict readable with ``torch.load(weights_only=True)`` (tensors, dicts, lists, str,
numbers only: no pickled code runs on load)::

    {"format": "gnssfuse-checkpoint", "format_version": 1,
     "config": {"model": {"kind": ..., "hparams": {...}}, "features": FeatureConfig dict,
                "eta": ..., "data": ..., "seed": ..., ...},
     "model_state": state_dict, "optimizer_state": ... | None, "epoch": int, "history": [...]}

Every save also writes the weights and config as ``<name>.npz`` beside it (:mod:`learned.npz_weights`): what
inference reads without torch.
"""
from __future__ import annotations

import os
import pickle
from pathlib import Path

import torch
from torch import nn

from fusion.errors import CheckpointError
from learned.model import MODELS, build_model
from learned.npz_weights import check_config, check_torch_file, file_sha256, npz_path_for, write_npz

FORMAT = "gnssfuse-checkpoint"
FORMAT_VERSION = 1


def save_checkpoint(path: str | Path, model: nn.Module, config: dict, *, optimizer_state: dict | None = None,
                    epoch: int = 0, history: list | None = None, extra: dict | None = None) -> Path:
    """Write atomically (temp file + rename) so an interrupted save never leaves a truncated checkpoint.
    ``extra``: more entries of tensors (what a resumable run needs beside its weights, :mod:`learned.train`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {"format": FORMAT, "format_version": FORMAT_VERSION, "config": config,
            "model_state": model.state_dict(), "optimizer_state": optimizer_state,
            "epoch": int(epoch), "history": list(history or [])}
    blob.update(extra or {})
    tmp = path.with_name(path.name + ".tmp")
    torch.save(blob, tmp)
    os.replace(tmp, path)
    # inference reads this twin and never imports torch (learned.npz_weights)
    write_npz(npz_path_for(path), {k: v.detach().cpu().float().numpy() for k, v in model.state_dict().items()},
              config, epoch, file_sha256(path))
    return path


def read_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Load and validate the container (not the weights). Raises CheckpointError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: " + ("a folder, not a checkpoint file" if path.is_dir()
                                             else "checkpoint file not found"))
    check_torch_file(path)
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        # weights_only refuses arbitrary objects (code could run on unpickling): never load those.
        raise CheckpointError(f"{path}: refused to load: holds objects other than tensors and plain "
                              "containers") from exc
    except Exception as exc:  # torch raises many types for bad zips / legacy pickles / short files
        raise CheckpointError(f"{path}: not a readable checkpoint (corrupt or truncated file?): "
                              f"{type(exc).__name__}") from exc
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a gnssfuse checkpoint (missing format tag {FORMAT!r})")
    if blob.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {blob.get('format_version')!r}, "
                              f"this code reads {FORMAT_VERSION}")
    check_config(blob.get("config"), path, MODELS)
    if not isinstance(blob.get("model_state"), dict):
        raise CheckpointError(f"{path}: checkpoint has no model weights")
    return blob


def load_model(path: str | Path, map_location: str | torch.device = "cpu") -> tuple[nn.Module, dict]:
    """Rebuild the model from the checkpoint's config and load its weights (strict).

    Returns ``(model in eval mode, blob)``. Architecture mismatches become CheckpointError.
    """
    blob = read_checkpoint(path, map_location)
    mcfg = blob["config"]["model"]
    try:
        model = build_model(mcfg["kind"], **mcfg.get("hparams", {}))
    except (TypeError, ValueError, AssertionError, RuntimeError) as exc:
        # torch's layers refuse bad sizes with any of these (e.g. heads not dividing the width: AssertionError)
        raise CheckpointError(f"{path}: model hyper-parameters do not fit this code: "
                              f"{type(exc).__name__}: {str(exc)[:200]}") from exc
    try:
        model.load_state_dict(blob["model_state"], strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()
        raise CheckpointError(f"{path}: architecture mismatch between checkpoint weights and "
                              f"{mcfg['kind']!r} model: {' '.join(first[:3])[:300]}") from exc
    model.to(map_location).eval()
    return model, blob
