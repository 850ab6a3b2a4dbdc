"""``gnssfuse`` command line: the dispatcher.

Every subcommand is one thin module in this package (``run``, ``evaluate``, ``simulate``,
``train``, ``adapt``, ``train-doppler``) exposing ``main(argv, prog) -> int``: it parses its arguments and calls the library.
The dispatcher names each by a ``"module:function"`` string and imports it only when that
subcommand runs, so ``gnssfuse run --mode wls`` never imports torch. Options several subcommands
share are defined once in :mod:`fusion.options`. Adding a subcommand is one module here and one line
in :data:`COMMANDS`.
"""
from __future__ import annotations

import gc
import importlib
import os
import sys
import threading
import warnings

from fusion.errors import GnssfuseError

#: subcommand -> ("module:function", one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("fusion.cli.run:main", "solve one trace in one mode (wls, dnn, fused, fused-nodnn)"),
    "evaluate": ("fusion.cli.evaluate:main", "compare modes on traces: tables, CDFs, box plots, report.md"),
    "simulate": ("fusion.cli.simulate:main", "simulate a GNSS trace (GSDC 2021 derived format + truth)"),
    "train": ("fusion.cli.train:main", "train the set-transformer correction network"),
    "adapt": ("fusion.cli.adapt:main", "fine-tune the learned models on logs without ground truth"),
    "train-doppler": ("fusion.cli.train_doppler:main", "train the learned Doppler head on logs with truth"),
}


def version() -> str:
    """The installed package's version ("unknown" when run from a source tree that is not installed)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version
    try:
        return dist_version("gnssfuse")
    except PackageNotFoundError:
        return "unknown"


def _usage() -> str:
    lines = ["usage: gnssfuse COMMAND [options]   (gnssfuse COMMAND --help for each)",
             "       gnssfuse --version", "", "commands:"]
    lines += [f"  {name:<13} {help_}" for name, (_, help_) in COMMANDS.items()]
    return "\n".join(lines)


#: glibc ``mallopt`` parameters: M_TRIM_THRESHOLD, M_MMAP_THRESHOLD.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def keep_freed_memory(mmap_above: int = 1 << 25, trim_above: int = 1 << 28) -> bool:
    """Have glibc's allocator serve blocks up to ``mmap_above`` bytes from its heap and keep up to
    ``trim_above`` bytes of freed heap for reuse, instead of mapping each large block afresh and giving
    it back when freed (``mallopt``; the ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` tunables).

    By default each new temporary array of a reader or a Gauss-Newton step over 128 kB is pages the
    kernel must fault in again: this takes ~40 % of the page faults of loading the Pixel5 log in
    ``gnssfuse run --mode wls`` (12,000 -> 7,600, ~12 ms; more on a virtual machine, where a fresh page
    is dear). For a short process (``run``, from :func:`entry`): its memory is its peak either way.
    True when both settings took; False where the C library has no ``mallopt`` (not glibc).
    """
    try:
        import ctypes
        libc = ctypes.CDLL(None)
        took = [libc.mallopt(_M_MMAP_THRESHOLD, mmap_above), libc.mallopt(_M_TRIM_THRESHOLD, trim_above)]
    except (OSError, AttributeError):
        return False
    return all(took)


def _import_quietly(module: str):
    """Import a subcommand's module with the cyclic garbage collector paused, then move everything
    imported so far out of its reach (``gc.freeze``). Imports allocate hundreds of thousands of
    long-lived objects (pandas, numpy, the library): without this the collector walks them again
    and again while they load, and once more at interpreter exit, about 70 ms of a ~0.6 s
    ``gnssfuse run --mode wls`` (``benchmarks/bench_pixel5.py``). Objects made later are collected
    as usual."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        return importlib.import_module(module)
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    if argv[0] in ("-V", "--version"):
        print(f"gnssfuse {version()}")
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"gnssfuse: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module, func = COMMANDS[cmd][0].split(":")
    # a user's warning (a file read in part, navigation missing for a constellation) is one line naming
    # the command, not Python's file and source line
    warnings.formatwarning = lambda message, category, *args, **kwargs: f"gnssfuse {cmd}: warning: {message}\n"
    if cmd == "evaluate":
        from fusion.parallel import jobs_asked, start_early
        if jobs_asked(rest) > 1:
            start_early()        # the workers' imports then overlap this process's
    entry = getattr(_import_quietly(module), func)
    try:
        return int(entry(rest, prog=f"gnssfuse {cmd}") or 0)
    except (GnssfuseError, OSError) as exc:
        # One line, no traceback: the message already names the file/epoch and the problem
        # (OSError: a missing input, an unwritable output).
        print(f"gnssfuse {cmd}: error: {exc}", file=sys.stderr)
        return 2


def entry() -> None:
    """The ``gnssfuse`` script and ``python -m fusion.cli``: :func:`main`, then exit with its code.

    A ``run`` keeps freed memory for reuse (:func:`keep_freed_memory`), and the interpreter's teardown
    after it (freeing every module and object one by one, ~20 ms of a ~0.6 s ``run --mode wls``) is
    skipped: its files are closed and written, so once stdout and stderr are flushed ``os._exit`` ends
    the process at once. Other subcommands (worker pools, Dask clients, torch) and a ``run`` that left
    threads or child processes behind exit normally, with their exit handlers.
    """
    argv = sys.argv[1:]
    if argv[:1] == ["run"]:
        keep_freed_memory()
    code = main(argv)
    if argv[:1] == ["run"] and threading.active_count() == 1 and not _children():
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        except (OSError, ValueError):       # a closed pipe: the ordinary exit reports it, as it always did
            sys.exit(code)
        os._exit(code)
    sys.exit(code)


def _children() -> bool:
    """Whether this process started child processes through :mod:`multiprocessing` that still run."""
    mp = sys.modules.get("multiprocessing")
    return mp is not None and bool(mp.active_children())
