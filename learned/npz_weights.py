"""The checkpoint's weights as a numpy ``.npz`` beside the ``.pt``: what inference reads, without torch.

The ``.npz`` holds every tensor of the model's state dict (float32 arrays under torch's names) and, under
``__config__``, the checkpoint's config as JSON text, plus ``__epoch__`` and ``__source_sha256__`` (the
SHA-256 of the ``.pt`` it was exported from). Training writes it beside every checkpoint it saves
(:func:`learned.checkpoint.save_checkpoint`); ``python -m learned.export CKPT.pt`` writes it for an older
checkpoint. :func:`load_for_inference` takes the ``.npz`` of a ``.pt`` when its recorded hash matches the
``.pt`` (a ``.pt`` copied over without its ``.npz`` falls back to reading the ``.pt`` with torch), so
``gnssfuse run`` never imports torch with shipped or freshly trained weights.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from fusion.errors import CheckpointError

FORMAT = "gnssfuse-npz"
_META = ("__format__", "__config__", "__epoch__", "__source_sha256__")


def npz_path_for(path: str | Path) -> Path:
    """``weights.pt`` -> ``weights.npz``; ``weights.pt.last`` -> ``weights.pt.last.npz``; a path ending in
    .npz is returned as is."""
    path = Path(path)
    if path.suffix == ".npz":
        return path
    return path.with_suffix(".npz") if path.suffix == ".pt" else path.with_name(path.name + ".npz")


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def write_npz(path: str | Path, weights: dict[str, np.ndarray], config: dict, epoch: int = 0,
              source_sha256: str = "") -> Path:
    """Write weights (name -> array) and config atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    bad = [k for k in weights if k in _META]
    if bad:
        raise CheckpointError(f"{path}: weight names {bad} clash with the npz metadata keys")
    tmp = path.with_name(path.name + ".tmp.npz")
    arrays = {k: np.asarray(v, np.float32) for k, v in weights.items()}
    np.savez(tmp, __format__=np.array(FORMAT), __config__=np.array(json.dumps(config)),
             __epoch__=np.array(int(epoch)), __source_sha256__=np.array(source_sha256), **arrays)
    os.replace(tmp, path)
    return path


def read_npz(path: str | Path) -> tuple[dict[str, np.ndarray], dict, str]:
    """(weights, config, source sha256) of an npz written by :func:`write_npz`; CheckpointError naming the
    file when it is not one."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: weights file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:          # numpy raises many types for bad zips / truncated files
        raise CheckpointError(f"{path}: not a readable .npz (corrupt or truncated?): {type(exc).__name__}") from exc
    if str(data.get("__format__", "")) != FORMAT:
        raise CheckpointError(f"{path}: not a gnssfuse weights file (missing format tag {FORMAT!r})")
    try:
        config = json.loads(str(data["__config__"]))
    except (KeyError, ValueError) as exc:
        raise CheckpointError(f"{path}: its config is missing or not JSON") from exc
    weights = {k: v for k, v in data.items() if k not in _META}
    return weights, config, str(data.get("__source_sha256__", ""))


def export_checkpoint(pt_path: str | Path, out: str | Path | None = None) -> Path:
    """Write the ``.npz`` of a ``.pt`` checkpoint (needs torch: training side only)."""
    from learned.checkpoint import read_checkpoint
    blob = read_checkpoint(pt_path)
    weights = {k: v.detach().cpu().float().numpy() for k, v in blob["model_state"].items()}
    return write_npz(out or npz_path_for(pt_path), weights, blob["config"], blob.get("epoch", 0),
                     file_sha256(pt_path))


def load_for_inference(path: str | Path) -> tuple[dict[str, np.ndarray], dict, Path]:
    """(weights, config, file read) for ``path`` (.npz, or .pt whose matching .npz is preferred)."""
    path = Path(path)
    if path.suffix == ".npz":
        weights, config, _ = read_npz(path)
        return weights, config, path
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    npz = npz_path_for(path)
    if npz.is_file():
        weights, config, sha = read_npz(npz)
        if sha == file_sha256(path):
            return weights, config, npz
    # no npz, or one exported from another .pt: read the .pt itself (imports torch)
    check_torch_file(path)
    try:
        from learned.checkpoint import read_checkpoint
    except ImportError as exc:
        raise CheckpointError(f"{path}: no matching .npz beside it and the .pt needs torch ({exc}): run "
                              f"`python -m learned.export {path}` where torch is installed, or pip install "
                              "'gnssfuse[train]'") from None
    blob = read_checkpoint(path)
    return {k: v.detach().cpu().float().numpy() for k, v in blob["model_state"].items()}, blob["config"], path


def check_torch_file(path: Path) -> None:
    """CheckpointError unless ``path`` starts as torch.save writes (a zip archive, or the older pickle):
    a text or JSON file passed as weights is named as such before torch is imported to read it."""
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head != b"PK\x03\x04" and head[:1] != b"\x80":
        raise CheckpointError(f"{path}: not a checkpoint (a .pt file is a zip archive written by torch.save; "
                              f"this one starts with {head!r})")


def check_config(config, path, kinds) -> None:
    """The checks every checkpoint's config passes before a network is built from it, torch or not: model
    and feature configs present, a feature version this code reads, a model kind among ``kinds``."""
    from fusion.errors import CheckpointError
    from learned.features import SUPPORTED_VERSIONS

    if not isinstance(config, dict) or not isinstance(config.get("model"), dict) \
            or not isinstance(config.get("features"), dict):
        raise CheckpointError(f"{path}: checkpoint has no model/feature config (or they are not dicts)")
    fv = config["features"].get("version")
    if fv not in SUPPORTED_VERSIONS:
        raise CheckpointError(f"{path}: feature version {fv!r}; this code reads versions {SUPPORTED_VERSIONS} "
                              "(retrain or use a matching gnssfuse version)")
    if config["model"].get("kind") not in kinds:
        raise CheckpointError(f"{path}: unknown model kind {config['model'].get('kind')!r}")
