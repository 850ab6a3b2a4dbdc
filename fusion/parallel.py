"""Traces in parallel processes: one worker process per job, one thread per worker.

Workers are not forked from the caller (a forked child of a process that has already started torch or
OpenMP threads can deadlock): on Linux they fork from a *forkserver*, a fresh single-threaded process that
has imported the pipeline once (``fusion.evaluate``: numpy, pandas, gtsam), so a worker starts in
milliseconds instead of re-importing for a second or more; elsewhere they are spawned. The server and
its workers are limited to one BLAS/OpenMP/torch thread each, so ``--jobs N`` uses N cores, not N times
all of them. A trace whose worker raises, or dies, is reported as a failure of that trace;
the others go on.
"""
from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

from tqdm import tqdm

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _one_thread() -> None:
    """Worker initialiser: one thread for BLAS/OpenMP and torch, which read these variables when
    first imported (after this, in a fresh spawned process; importing torch here would cost every
    worker seconds even when no mode needs it)."""
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    if "torch" in sys.modules:  # pragma: no cover - not in a spawned worker, but cheap to be sure
        sys.modules["torch"].set_num_threads(1)


def map_traces(func: Callable, args: Sequence[tuple], jobs: int, progress: bool = False) -> list:
    """``[func(*a) for a in args]`` in ``jobs`` spawned processes, results in the order of ``args``.

    ``func`` must be importable by name (a module-level function). An exception in one call becomes
    that call's result as the string ``"worker failed: <type>: <message>"``.
    """
    out: list = [None] * len(args)
    ctx = _context()
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update({v: "1" for v in _THREAD_VARS})      # inherited by the forkserver when it starts
    try:
        return _run_pool(func, args, jobs, ctx, out, progress)
    finally:
        for v, old in saved.items():
            if old is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = old


def _context():
    """A forkserver preloaded with the pipeline where the platform has one, else spawn."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["fusion.evaluate"])
        return ctx
    return multiprocessing.get_context("spawn")


def _run_pool(func: Callable, args: Sequence[tuple], jobs: int, ctx, out: list, progress: bool) -> list:
    """The pool loop of :func:`map_traces`, filling ``out`` in the order of ``args``."""
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_one_thread) as pool:
        futures = {pool.submit(func, *a): i for i, a in enumerate(args)}
        for fut in tqdm(as_completed(futures), total=len(futures), desc="traces", disable=not progress):
            i = futures[fut]
            try:
                out[i] = fut.result()
            except BrokenProcessPool as exc:
                out[i] = f"worker failed: the worker process died ({exc})"
            except Exception as exc:  # noqa: BLE001 - one trace's crash must not stop the others
                out[i] = f"worker failed: {type(exc).__name__}: {exc}"
    return out
