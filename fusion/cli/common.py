"""What every subcommand module needs: output paths checked up front (errors naming the option),
the library named by ``"module:function"`` strings (for the ``learned`` side, which ``fusion`` never
imports), and progress bars only on a terminal."""
from __future__ import annotations

import importlib
import sys
from pathlib import Path

from fusion.errors import GnssfuseError, ModeUnavailableError


def _make_folder(folder: Path, what: str) -> None:
    """mkdir -p ``folder``; a :class:`GnssfuseError` starting with ``what`` when it cannot be made."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise GnssfuseError(f"{what}: {folder} or a folder above it is a file, not a folder") from None
    except OSError as exc:
        raise GnssfuseError(f"{what}: cannot create {folder} ({exc.strerror or exc})") from None


def out_folder(path: Path, option: str = "--out") -> Path:
    """Create the output folder ``path`` (and its parents) before any work, so that a bad one is a
    one-line error naming ``option`` rather than an ``[Errno 17]`` after a long run."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise GnssfuseError(f"{option} {path}: is a file, not a folder")
    _make_folder(path, f"{option} {path}")
    return path


def out_file(path: Path, option: str = "--out") -> Path:
    """Check that the file ``path`` can be written (its folder is created): a one-line error naming
    ``option`` when it is a folder or its folder cannot be made."""
    path = Path(path)
    if path.is_dir():
        raise GnssfuseError(f"{option} {path}: is a folder; give a file path")
    _make_folder(path.parent, f"{option} {path}")
    return path


def call(target: str, *args, **kwargs):
    """Import ``"module:function"`` and call it (how a subcommand reaches ``learned``); a missing
    module (e.g. torch not installed) is a one-line :class:`ModeUnavailableError`."""
    module, func = target.split(":")
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        hint = "; training needs torch: pip install 'gnssfuse[train]'" if exc.name == "torch" else ""
        raise ModeUnavailableError(f"cannot import {module} ({exc}){hint}") from exc
    return getattr(mod, func)(*args, **kwargs)


def learned_work(target: str, args, prog: str) -> int:
    """A subcommand whose work lives in ``learned`` (train, adapt): its ``--out`` file checked up front,
    then ``target`` called with the parsed ``args``, a progress bar unless ``--quiet`` or not a terminal."""
    out_file(args.out)
    return call(target, args, prog=prog, progress=show_progress(not args.quiet))


def show_progress(asked: bool = True) -> bool:
    """Progress bars only when asked and stderr is a terminal: a log file or pipe gets no ``\\r`` bars
    or escape codes."""
    return asked and sys.stderr.isatty()
